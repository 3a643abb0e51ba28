"""Recordings: ``dammrl recording info|repair|export|human|plot|video|decode`` and
``dammrl replay``."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from dammrl.cli.common import (
    CONNECT_HELP,
    FIGURE_SUFFIXES,
    Commands,
    add_connect,
    bus_settings,
    check_video_path,
    headless_gl,
    output_file,
    print_err,
    progress_bar,
)
from dammrl_core.errors import Exit, UsageError


def register(commands: Commands) -> None:
    """Add ``recording`` and its actions, then ``replay``."""
    recording = commands.add_parser("recording", help="inspect, repair and export recordings")
    actions = recording.add_subparsers(required=True, metavar="ACTION")
    info = actions.add_parser("info", help="topics, counts, rates, duration, gaps, metadata")
    info.add_argument("file", type=Path, help="an MCAP recording")
    info.add_argument("--json", action="store_true", help="one JSON object")
    info.set_defaults(handler=_info)
    repair = actions.add_parser("repair", help="rewrite a cut recording as a complete MCAP")
    repair.add_argument("file", type=Path, help="a damaged MCAP recording")
    repair.add_argument("-o", "--out", type=output_file(".mcap"),
                        help="default: <file>.repaired.mcap")  # fmt: skip
    repair.set_defaults(handler=_repair)
    _add_export(actions)
    human = actions.add_parser("human", help="the human's error rate per radius, decision rate")
    human.add_argument("file", type=Path, help="an MCAP recording")
    human.add_argument("--json", action="store_true", help="one JSON object")
    human.set_defaults(handler=_human)
    _add_plot(actions)
    _add_decode(actions)
    _add_replay(commands)


def _add_decode(actions: Commands) -> None:
    decode = actions.add_parser(
        "decode",
        help="decode a recorded wearable stream again, with a (another) person's classifier",
        description="Run a calibration's classifier over the raw stream a session recorded "
        "(sensor/chunk) or an XDF file (LabRecorder's), as the live source would: one row "
        "per decision; with a session, how many match the decisions made live.",
    )
    decode.add_argument("file", type=Path, help="an MCAP recording or an .xdf file")
    decode.add_argument("--calibration", type=Path, required=True,
                        help="from `dammrl intent calibrate`")  # fmt: skip
    decode.add_argument("--stream", help="the stream's name (when there are several)")
    decode.add_argument("--csv", type=output_file(".csv"), help="also write the decisions here")
    decode.set_defaults(handler=_decode)


def _add_export(actions: Commands) -> None:
    export = actions.add_parser("export", help="JSON-encoded MCAP (Foxglove) or CSV per topic")
    export.add_argument("file", type=Path, help="an MCAP recording")
    export.add_argument("--format", choices=["json", "csv"], required=True,
                        help="json: one file; csv: one file per topic")  # fmt: skip
    export.add_argument(
        "-o", "--out", type=Path, required=True, help="file (json) or directory (csv)"
    )
    export.set_defaults(handler=_export)


def _add_plot(actions: Commands) -> None:
    plot = actions.add_parser(
        "plot", help="pressure trace above the end-effector error (the paper's S2 figure)"
    )
    plot.add_argument("file", type=Path, help="an MCAP recording")
    plot.add_argument("-o", "--out", type=output_file(*FIGURE_SUFFIXES), required=True,
                      metavar="PNG", help="the figure (.png, .pdf, .svg, .jpg)")  # fmt: skip
    plot.add_argument("--episode", type=int, help="only this episode")
    plot.set_defaults(handler=_plot)
    video = actions.add_parser("video", help="render an episode of a recording (MP4 or GIF)")
    video.add_argument("file", type=Path, help="an MCAP recording")
    video.add_argument("-o", "--out", type=output_file(), required=True,
                       metavar="MP4|GIF",
                       help="the video (.mp4 needs dammrl[video])")  # fmt: skip
    video.add_argument("--episode", type=int, help="this episode (default: the first)")
    video.add_argument("--fps", type=int, default=25, help="frames per second (default 25)")
    video.add_argument("--speed", type=float, default=1.0,
                       help="playback speed (2: twice real time; default 1)")  # fmt: skip
    video.set_defaults(handler=_video)


def _add_replay(commands: Commands) -> None:
    replay = commands.add_parser("replay", help="publish a recording onto the bus")
    replay.add_argument("file", type=Path, help="an MCAP recording")
    replay.add_argument(
        "--rate", type=float, default=1.0, help="1 real time, 0 as fast as possible"
    )
    replay.add_argument("--topics", help="comma-separated topic prefixes, e.g. intent,robot/state")
    replay.add_argument("--start", type=float, default=0.0, help="offset into the recording [s]")
    replay.add_argument("--end", type=float, help="offset where to stop [s]")
    replay.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    replay.add_argument("--namespace", help="publish under this namespace (default: recorded one)")
    add_connect(replay, CONNECT_HELP)
    replay.add_argument("--force", action="store_true", help="replay commands even to a live arm")
    replay.add_argument("--into-policy", type=Path, metavar="RUN",
                        help="offline, no bus: a trained policy's choice at every recorded "
                             "decision, next to the recorded one (a run directory, .pt, or a "
                             "shipped policy: reward1, reward2)")  # fmt: skip
    replay.add_argument("-o", "--out", type=output_file(".csv"),
                        help="with --into-policy: the CSV of decisions (default: beside the "
                             "recording, <name>.decisions.csv)")  # fmt: skip
    replay.set_defaults(handler=_replay)


def _info(args: argparse.Namespace) -> int:
    """Topics, counts, rates, duration, gaps and metadata, as text or JSON."""
    from dammrl.stack.recording import info

    summary = info(args.file)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    state = "complete" if summary["complete"] else f"NOT finished ({summary['truncated']})"
    print(
        f"{summary['file']}: {summary['messages']} messages, {summary['duration_s']:.1f} s, {state}"
    )
    for topic, t in summary["topics"].items():
        print(f"  {topic:36s} {t['type']:16s} {t['count']:8d}  {t['rate_hz']:8.1f} Hz")
    gaps = summary["sequence_gaps"]
    print("  sequence gaps: " + (", ".join(f"{k} {v}" for k, v in gaps.items()) or "none"))
    for kind, counts in summary["sequence_anomalies"].items():
        print(f"  {kind.replace('_', ' ')}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    for stream, raw in summary["raw_streams"].items():
        print(
            f"  raw stream {stream!r}: {raw['samples']} samples, {raw['missing_samples']} "
            f"missing in {raw['gaps']} gaps, {raw['clock_jumps']} clock jumps corrected"
        )
    if summary["skipped"]:
        print("  skipped (unreadable): " + _counts(summary["skipped"]))
    for name, data in summary["metadata"].items():
        print(
            f"  metadata {name}: "
            + ", ".join(f"{k}={v}" for k, v in data.items() if k != "settings")
        )
    return 0


def _repair(args: argparse.Namespace) -> int:
    """Rewrite a cut recording as a complete MCAP."""
    from dammrl.stack.recording import repair

    out = args.out or args.file.with_suffix(".repaired.mcap")
    done = repair(args.file, out)
    state = "complete" if done["was_complete"] else f"cut: {done['why']}"
    print(f"wrote {done['messages']} messages to {out} (source {state})")
    if done["skipped"]:
        print(f"skipped (unreadable): {_counts(done['skipped'])}")
    return 0


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{n} {what}" for what, n in counts.items())


def _export(args: argparse.Namespace) -> int:
    """One JSON-encoded MCAP, or one CSV per topic."""
    from dammrl.stack.recording import export_csv, export_json, read_recording

    total = len(read_recording(args.file).messages)
    update, close = progress_bar(total, f"export {args.format}", "message")
    try:
        if args.format == "json":
            written = export_json(args.file, args.out, update)
        else:
            tables = export_csv(args.file, args.out, update)
    finally:
        close()
    if args.format == "json":
        print(f"wrote {written} JSON messages to {args.out}")
    else:
        for topic, rows in tables.items():
            print(f"{topic}: {rows} rows")
    return 0


def _plot(args: argparse.Namespace) -> int:
    """The pressure trace above the end-effector error; prints the figure's path."""
    from dammrl.stack.recording import session_traces
    from dammrl.views.plots import plot_session
    from dammrl_core.task import TaskSettings

    traces = session_traces(args.file, args.episode)
    title = f"{args.file.name}: {len(traces.decisions)} decisions, {len(traces.pressure)} samples"
    print(plot_session(traces, TaskSettings().goal_tolerance_m, title, args.out))
    return 0


def _video(args: argparse.Namespace) -> int:
    """Render one episode of a recording offscreen; prints the video's path."""
    check_video_path(args.out)
    headless_gl()  # before MuJoCo is imported
    from dammrl.views.video import VideoSettings, frame_times, track_of_recording, write_video

    if not args.file.is_file():
        raise FileNotFoundError(f"no such recording: {args.file}")
    track = track_of_recording(args.file, args.episode)
    settings = VideoSettings(fps=args.fps, speed=args.speed)
    settings.check()
    update, close = progress_bar(len(frame_times(track, settings)), "video", "frame")
    try:
        frames = write_video(track, args.out, settings, update)
    finally:
        close()
    print_err(f"{frames} frames of {track.label}")
    print(args.out)
    return 0


def _human(args: argparse.Namespace) -> int:
    """The human's decision rate and, per radius, error rate and decision time."""
    from dammrl.stack.recording import human_statistics

    stats = human_statistics(args.file)
    if args.json:
        print(json.dumps(stats))
        return 0
    print(f"{stats['decisions']} decisions, {stats['decision_frequency_hz']:.2f} per second")
    for radius, r in stats["per_radius"].items():
        print(f"  {radius:8s} {r['decisions']:5d} decisions, error rate {r['error_rate']:.3f}, "
              f"mean decision time {r['mean_decision_s']:.2f} s")  # fmt: skip
    return 0


def _decode(args: argparse.Namespace) -> int:
    """Decisions of a recorded stream under a calibration; agreement with the live ones."""
    from dammrl.devices.wearable import (
        decode_signal,
        live_onsets,
        signal_of_recording,
        signal_of_xdf,
        write_csv,
    )
    from dammrl_core.intent.emg.calibration import load_calibration

    calibration = load_calibration(args.calibration)
    xdf = args.file.suffix.lower() == ".xdf"
    signal = (signal_of_xdf if xdf else signal_of_recording)(args.file, args.stream)
    found = decode_signal(signal, calibration)
    rows = [{"onset_s": round(c.onset_s - signal.times_s[0], 3), "u_h": c.u_h,
             "human_model": c.human_model, "duration_s": round(c.duration_s, 3),
             "confidence": round(c.confidence, 3), "acted_on": c.accepted,
             "reason": c.reason} for c in found]  # fmt: skip
    for row in rows:
        print("  ".join(f"{k} {v}" for k, v in row.items() if v != ""))
    print(f"{len(found)} decisions ({sum(c.accepted for c in found)} would be acted on) in "
          f"{signal.times_s[-1] - signal.times_s[0]:.1f} s of {signal.name!r}")  # fmt: skip
    if not xdf:
        live = live_onsets(args.file)
        matched = sum(any(abs(c.onset_s - t) < 0.1 for t in live) for c in found if c.accepted)
        print(f"live decisions in the recording: {len(live)}; matched here: {matched}")
    if args.csv is not None:
        write_csv(rows, args.csv)
        print(f"decisions written to {args.csv}")
    return Exit.OK


def _replay(args: argparse.Namespace) -> int:
    """Publish a recording onto the bus, or (``--into-policy``) compare a policy offline."""
    from dammrl.stack.recording import read_recording
    from dammrl.stack.replay import ReplayOptions, into_policy, replay, selected, write_decisions
    from services.common.runtime import stopping_on_signals

    recording = read_recording(args.file)
    if args.into_policy is not None:
        out = args.out or args.file.with_suffix(".decisions.csv")
        if not os.access(out.parent, os.W_OK):  # -o was checked as it was parsed
            raise UsageError(f"{out.parent} cannot be written: give -o FILE.csv")
        summary = write_decisions(into_policy(recording, args.into_policy), out)
        print(json.dumps(summary | {"csv": str(out)}))
        return 0
    options = ReplayOptions(
        rate=args.rate, topics=tuple(filter(None, (args.topics or "").split(","))),
        start_s=args.start, end_s=args.end, loop=args.loop, force=args.force,
    )  # fmt: skip
    settings = bus_settings(args, recording.namespace())
    total = None if options.loop else len(selected(recording, options))
    update, close = progress_bar(total, "replay", "message")
    try:
        with stopping_on_signals() as stop:  # Ctrl-C ends the replay, not the process
            sent = replay(recording, settings, options, print_err, stop, update)
    finally:
        close()
    print(f"replayed {sent} messages")
    if stop.is_set() and not options.loop:  # a finite job cut short
        print_err("dammrl: interrupted")
        return Exit.INTERRUPTED
    return Exit.OK
