"""The ``dammrl`` command: the researcher's front door."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import ValidationError

from dammrl.core.errors import DammrlError

if TYPE_CHECKING:
    from services.common.config import BusSettings
    from services.intent.emulator import SensorEmulator
from dammrl.core.models import parse_model


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args))
    except DammrlError as exc:
        print(f"dammrl: error: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:  # a setting (flag or DAMMRL_* variable) out of range
        print(f"dammrl: invalid settings: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a path given on the command line: unwritable, missing, busy
        print(f"dammrl: error: {exc}", file=sys.stderr)
        return 2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dammrl", description="Event-triggered human-robot co-adaptation (DAMMRL)."
    )
    commands = parser.add_subparsers(required=True, metavar="COMMAND")
    reach = commands.add_parser(
        "reach",
        help="run one simulated reach in-process and print its metrics",
        description="One reach of the button-press task, sim + simulated human, no bus.",
    )
    reach.add_argument(
        "--trigger",
        choices=["event", "fixed", "both"],
        default="event",
        help="progression: event trigger, fixed-frequency baseline, or both",
    )
    reach.add_argument(
        "--model",
        type=_model_arg,
        default=(1, 1),
        metavar="I,J",
        help="multi-model M_ij: I=1 E_big, I=2 E_small; J=1..8 step vector "
        "(J-1 in binary = large on x,y,z; 1 all-small, 8 all-large)",
    )
    reach.add_argument("--seed", type=int, default=0, help="seed of start/goal, human, latency")
    reach.add_argument("--json", action="store_true", help="one JSON object per reach")
    reach.add_argument("--plot", type=Path, metavar="PNG", help="save a trajectory figure")
    reach.add_argument("--ik", choices=["pinocchio", "ikpy"], help="IK solver (default pinocchio)")
    reach.add_argument("--feedforward", choices=["inverse_dynamics", "resolved_acceleration"])
    reach.add_argument("--randomize", action="store_true", help="seeded domain randomisation")
    reach.set_defaults(handler=_reach)

    up = commands.add_parser(
        "up",
        help="launch the service stack of a mode",
        description="Start the services as processes on the bus; Ctrl-C stops them all.",
    )
    up.add_argument("--mode", choices=["virtual", "semi-virtual"], default="virtual")
    up.add_argument(
        "--episodes", type=int, help="run this many episodes, then stop (default: until Ctrl-C)"
    )
    up.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    up.add_argument("--model", type=_model_arg, metavar="I,J",
                    help="a fixed M_ij (default: the learned DAMMRL policy)")  # fmt: skip
    up.add_argument("--trigger", choices=["event", "fixed"], default="event")
    up.add_argument("--port", help="semi-virtual: the pressure sensor's serial device")
    up.add_argument("--calibration", type=Path,
                    help="semi-virtual: file from `dammrl sensor calibrate`")  # fmt: skip
    up.add_argument(
        "--bus-port", type=int, default=7447, help="loopback port of the stack's endpoint"
    )
    up.add_argument("--namespace", default="dammrl")
    up.add_argument("--json", action="store_true", help="one JSON object per episode")
    up.add_argument(
        "--record", type=Path, metavar="MCAP", help="also run the recorder into this file"
    )
    up.set_defaults(handler=_up)

    for name, helptext in (
        ("status", "services alive on the bus, their health and rates"),
        ("echo", "print the decoded messages of one topic"),
    ):
        sub = commands.add_parser(name, help=helptext, description=helptext)
        sub.add_argument(
            "--connect",
            action="append",
            metavar="ENDPOINT",
            help="where the stack listens (default tcp/127.0.0.1:7447)",
        )
        sub.add_argument("--namespace", default="dammrl")
        if name == "echo":
            sub.add_argument("topic", help="e.g. robot/state, task/result, health/*")
            sub.add_argument("--hz", action="store_true", help="print the rate instead")
            sub.add_argument("--count", type=int, help="stop after this many messages")
            sub.add_argument("--duration", type=float, help="stop after this many seconds")
        sub.set_defaults(handler=_status if name == "status" else _echo)

    _add_recording_commands(commands)

    _add_sensor_commands(commands)

    train = commands.add_parser("train", help="train the dual-agent DQN (DAMMRL)")
    train.add_argument("--reward", type=int, choices=[1, 2], required=True,
                       help="1: accuracy focus (beta = 0); 2: speed and accuracy")  # fmt: skip
    train.add_argument("--out", type=Path, required=True, help="run directory (resumes if present)")
    train.add_argument("--episodes", type=int, help="default 1500 (DAMMRL_RL_EPISODES)")
    train.add_argument("--seed", type=int)
    train.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    train.set_defaults(handler=_train)
    evaluate = commands.add_parser("evaluate", help="greedy evaluation of a trained run")
    evaluate.add_argument("--checkpoint", type=Path, required=True, help="run directory or .pt")
    evaluate.add_argument("--episodes", type=int, default=100)
    evaluate.add_argument("--json", action="store_true")
    evaluate.set_defaults(handler=_evaluate)

    schemas = commands.add_parser("schemas", help="write the JSON Schema of every message")
    schemas.add_argument("--out", type=Path, required=True, metavar="DIR")
    schemas.set_defaults(handler=_schemas)
    return parser


def _add_sensor_commands(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sensor = commands.add_parser("sensor", help="the pressure sensor (semi-virtual mode)")
    actions = sensor.add_subparsers(required=True, metavar="ACTION")
    listing = actions.add_parser("list", help="serial ports found, with descriptions")
    listing.set_defaults(handler=_sensor_list)

    calibrate = actions.add_parser(
        "calibrate",
        help="guided: rest, light press, firm press; saves a calibration file",
        description="Record the pad at rest, under a light and under a firm press, and save "
        "the calibration the intent service reads (DAMMRL_INTENT_CALIBRATION_FILE).",
    )
    calibrate.add_argument("--port", required=True, help="serial device, e.g. /dev/ttyUSB0")
    calibrate.add_argument("--out", type=Path, default=Path("sensor_calibration.json"),
                           help="where to save it (default sensor_calibration.json)")  # fmt: skip
    calibrate.add_argument("--seconds", type=_positive, default=3.0, help="recording per step [s]")
    calibrate.add_argument("--yes", action="store_true",
                           help="do not wait for Enter before each step (scripts)")  # fmt: skip
    calibrate.set_defaults(handler=_sensor_calibrate)

    monitor = actions.add_parser(
        "monitor", help="live pressure, decoded command and radius choice (until Ctrl-C)"
    )
    monitor.add_argument("--port", required=True, help="serial device, e.g. /dev/ttyUSB0")
    monitor.add_argument(
        "--calibration", type=Path, help="calibration file (default DAMMRL_INTENT_CALIBRATION_FILE)"
    )
    monitor.add_argument("--seconds", type=_positive, help="stop after this long")
    monitor.set_defaults(handler=_sensor_monitor)

    emulate = actions.add_parser(
        "emulate",
        help="a virtual sensor on a pseudo-terminal (until Ctrl-C)",
        description="A virtual pressure sensor: frames of the wire protocol on a "
        "pseudo-terminal linked at --link, which the stack opens like a real port.",
    )
    emulate.add_argument("--link", type=Path, default=Path("/tmp/ttySENSOR"),
                         help="path the emulated port appears at")  # fmt: skip
    emulate.add_argument(
        "--pattern",
        choices=["taps", "keyboard", "patient"],
        default="taps",
        help="taps: a quick firm press every --period s; keyboard: you press keys; "
        "patient: a simulated patient answers the stack's decision requests",
    )
    emulate.add_argument(
        "--period", type=_positive, default=1.0, help="taps: seconds between presses"
    )
    emulate.add_argument("--patient-model", type=int, choices=[1, 2], default=2,
                         help="patient: 1 hurried (quick presses, E_big), 2 careful (held, "
                         "E_small)")  # fmt: skip
    emulate.add_argument("--seed", type=int, default=0, help="patient's decisions, ADC noise")
    emulate.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="patient: the stack's endpoint (default tcp/127.0.0.1:7447)",
    )
    emulate.add_argument("--namespace", default="dammrl")
    emulate.add_argument("--rate", type=_positive, default=100.0, help="frames per second")
    emulate.add_argument("--seconds", type=_positive, help="stop after this long")
    emulate.set_defaults(handler=_sensor_emulate)


def _add_recording_commands(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    recording = commands.add_parser("recording", help="inspect, repair and export recordings")
    actions = recording.add_subparsers(required=True, metavar="ACTION")
    info = actions.add_parser("info", help="topics, counts, rates, duration, gaps, metadata")
    info.add_argument("file", type=Path)
    info.add_argument("--json", action="store_true")
    info.set_defaults(handler=_recording_info)
    repair = actions.add_parser("repair", help="rewrite a cut recording as a complete MCAP")
    repair.add_argument("file", type=Path)
    repair.add_argument("-o", "--out", type=Path, help="default: <file>.repaired.mcap")
    repair.set_defaults(handler=_recording_repair)
    export = actions.add_parser("export", help="JSON-encoded MCAP (Foxglove) or CSV per topic")
    export.add_argument("file", type=Path)
    export.add_argument("--format", choices=["json", "csv"], required=True)
    export.add_argument(
        "-o", "--out", type=Path, required=True, help="file (json) or directory (csv)"
    )
    export.set_defaults(handler=_recording_export)
    human = actions.add_parser("human", help="the human's error rate per radius, decision rate")
    human.add_argument("file", type=Path)
    human.add_argument("--json", action="store_true")
    human.set_defaults(handler=_recording_human)

    plot = actions.add_parser(
        "plot", help="pressure trace above the end-effector error (the paper's S2 figure)"
    )
    plot.add_argument("file", type=Path)
    plot.add_argument("-o", "--out", type=Path, required=True, metavar="PNG")
    plot.add_argument("--episode", type=int, help="only this episode")
    plot.set_defaults(handler=_recording_plot)

    replay = commands.add_parser("replay", help="publish a recording onto the bus")
    replay.add_argument("file", type=Path)
    replay.add_argument(
        "--rate", type=float, default=1.0, help="1 real time, 0 as fast as possible"
    )
    replay.add_argument("--topics", help="comma-separated topic prefixes, e.g. intent,robot/state")
    replay.add_argument("--start", type=float, default=0.0, help="offset into the recording [s]")
    replay.add_argument("--end", type=float, help="offset where to stop [s]")
    replay.add_argument("--loop", action="store_true")
    replay.add_argument("--namespace", help="publish under this namespace (default: recorded one)")
    replay.add_argument("--connect", action="append", metavar="ENDPOINT",
                        help="default tcp/127.0.0.1:7447")  # fmt: skip
    replay.add_argument("--force", action="store_true", help="replay commands even to a live arm")
    replay.add_argument("--into-policy", type=Path, metavar="RUN",
                        help="offline, no bus: a trained policy's choice at every recorded "
                             "decision, next to the recorded one")  # fmt: skip
    replay.add_argument("-o", "--out", type=Path, default=Path("decisions.csv"),
                        help="with --into-policy: the CSV of decisions")  # fmt: skip
    replay.set_defaults(handler=_replay)


def _recording_info(args: argparse.Namespace) -> int:
    from dammrl.recording import info

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
    for name, data in summary["metadata"].items():
        print(
            f"  metadata {name}: "
            + ", ".join(f"{k}={v}" for k, v in data.items() if k != "settings")
        )
    return 0


def _recording_repair(args: argparse.Namespace) -> int:
    from dammrl.recording import repair

    out = args.out or args.file.with_suffix(".repaired.mcap")
    done = repair(args.file, out)
    print(f"wrote {done['messages']} messages to {out} (source complete: {done['was_complete']})")
    return 0


def _recording_export(args: argparse.Namespace) -> int:
    from dammrl.recording import export_csv, export_json

    if args.format == "json":
        print(f"wrote {export_json(args.file, args.out)} JSON messages to {args.out}")
    else:
        for topic, rows in export_csv(args.file, args.out).items():
            print(f"{topic}: {rows} rows")
    return 0


def _recording_plot(args: argparse.Namespace) -> int:
    from dammrl.core.task import TaskSettings
    from dammrl.plots import plot_session
    from dammrl.recording import session_traces

    traces = session_traces(args.file, args.episode)
    title = f"{args.file.name}: {len(traces.decisions)} decisions, {len(traces.pressure)} samples"
    print(plot_session(traces, TaskSettings().goal_tolerance_m, title, args.out))
    return 0


def _recording_human(args: argparse.Namespace) -> int:
    from dammrl.recording import human_statistics

    stats = human_statistics(args.file)
    if args.json:
        print(json.dumps(stats))
        return 0
    print(f"{stats['decisions']} decisions, {stats['decision_frequency_hz']:.2f} per second")
    for radius, r in stats["per_radius"].items():
        print(f"  {radius:8s} {r['decisions']:5d} decisions, error rate {r['error_rate']:.3f}, "
              f"mean decision time {r['mean_decision_s']:.2f} s")  # fmt: skip
    return 0


def _replay(args: argparse.Namespace) -> int:
    from dammrl.recording import read_recording
    from dammrl.replay import ReplayOptions, replay
    from services.common.config import BusSettings

    recording = read_recording(args.file)
    if args.into_policy is not None:
        from dammrl.replay import into_policy, write_decisions

        summary = write_decisions(into_policy(recording, args.into_policy), args.out)
        print(json.dumps(summary | {"csv": str(args.out)}))
        return 0
    options = ReplayOptions(
        rate=args.rate, topics=tuple(filter(None, (args.topics or "").split(","))),
        start_s=args.start, end_s=args.end, loop=args.loop, force=args.force,
    )  # fmt: skip
    settings = BusSettings(
        connect=args.connect or ["tcp/127.0.0.1:7447"],
        namespace=args.namespace or recording.namespace(),
    )
    print(f"replayed {replay(recording, settings, options, info=_print_err)} messages")
    return 0


def _train(args: argparse.Namespace) -> int:
    from dammrl.rl.config import TrainSettings
    from dammrl.rl.train import train

    overrides = {k: v for k in ("episodes", "seed") if (v := getattr(args, k)) is not None}
    settings = TrainSettings(**overrides)
    logs = train(args.reward, args.out, settings, args.device, progress=_print_err)
    recent = logs[-50:]
    print(f"trained {len(logs)} episodes; last 50: success "
          f"{sum(r.success for r in recent) / len(recent):.0%}; run in {args.out}")  # fmt: skip
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from dammrl.rl.train import evaluate

    result = evaluate(args.checkpoint, args.episodes)
    if args.json:
        print(json.dumps(result))
    else:
        print("\n".join(f"{k:22s} {v}" for k, v in result.items()))
    return 0


def _sensor_list(args: argparse.Namespace) -> int:
    from serial.tools import list_ports

    ports = sorted(list_ports.comports(), key=lambda p: p.device)
    if not ports:
        print("no serial port found (a USB sensor appears as /dev/ttyUSB* or /dev/ttyACM*)")
    for port in ports:
        print(f"{port.device:20s} {port.description}  [{port.hwid}]")
    return 0


def _sensor_calibrate(args: argparse.Namespace) -> int:
    from dammrl.sensor import calibrate, quiet_reader
    from services.intent.serial_sensor import SerialSensor

    quiet_reader()
    if not args.out.parent.is_dir():  # say so before the person does three recordings
        raise DammrlError(f"cannot save the calibration: {args.out.parent} is not a directory")

    def ready(step: str) -> None:
        print(f"\n{step}")
        if not args.yes:
            input(f"  Press Enter to start the {args.seconds:.0f} s recording... ")

    def show(line: str) -> None:
        end = "\r" if line.startswith("  recording") else "\n"
        print(f"\x1b[2K{line}" if sys.stdout.isatty() else line, end=end, flush=True)

    print(f"Calibrating the pressure sensor on {args.port}: three {args.seconds:.0f} s recordings.")
    try:
        with SerialSensor(args.port, reconnect_max_s=1.0) as sensor:
            calibration = calibrate(sensor, args.seconds, ready, show)
    except (KeyboardInterrupt, EOFError):
        print("\ncalibration cancelled; nothing saved (--yes runs without Enter)")
        return 130
    args.out.write_text(calibration.model_dump_json(indent=2) + "\n")
    print(
        f"\nSaved {args.out}: rest {calibration.rest_raw:.0f}, light {calibration.light_raw:.0f},"
        f" firm {calibration.firm_raw:.0f} raw.\nCheck it:   dammrl sensor monitor --port "
        f"{args.port} --calibration {args.out}\nUse it:     DAMMRL_INTENT_CALIBRATION_FILE="
        f"{args.out.resolve()} dammrl up --mode semi-virtual --port {args.port}"
    )
    return 0


def _sensor_monitor(args: argparse.Namespace) -> int:
    from dammrl.core.models import ModelSet
    from dammrl.sensor import Monitor, quiet_reader, wait_for_frames
    from services.common.runtime import stop_on_signals
    from services.intent.calibration import load_calibration
    from services.intent.config import IntentSettings
    from services.intent.decoder import PressDecoder
    from services.intent.serial_sensor import SerialSensor

    quiet_reader()
    settings = IntentSettings()  # the intent service's settings: the same thresholds
    calibration = load_calibration(args.calibration or settings.calibration_file)
    stop = stop_on_signals()
    with SerialSensor(args.port, reconnect_max_s=1.0) as sensor:
        wait_for_frames(sensor)
        _stop_after(stop, args.seconds)
        Monitor(sensor, PressDecoder(calibration, settings.decoder), ModelSet()).run(stop)
    return 0


def _sensor_emulate(args: argparse.Namespace) -> int:
    from dammrl.sensor import KEYS, keyboard
    from services.common.runtime import stop_on_signals
    from services.intent.emulator import Press, SensorEmulator

    if args.pattern == "keyboard" and not sys.stdin.isatty():
        raise DammrlError("the keyboard pattern needs a terminal (run it in its own tmux pane)")
    stop = stop_on_signals()
    _stop_after(stop, args.seconds)
    script = [Press(0.2, 0.2, 1.0)] if args.pattern == "taps" else []
    loop_s = args.period if args.pattern == "taps" else None
    with SensorEmulator(args.link, script, loop_s=loop_s, seed=args.seed, rate_hz=args.rate) as pad:
        print(f"emulated sensor on {args.link} ({args.rate:.0f} frames/s); Ctrl-C stops")
        if args.pattern == "taps":
            print(f"a quick firm press (+1, E_big) every {args.period} s")
            stop.wait()
        elif args.pattern == "keyboard":
            print(KEYS, flush=True)
            keyboard(pad, stop)
        else:
            _patient(args, pad, stop)
        print(f"\nsent {pad.sent} frames")
    return 0


def _stop_after(stop: threading.Event, seconds: float | None) -> None:
    if seconds is not None:
        timer = threading.Timer(seconds, stop.set)
        timer.daemon = True
        timer.start()


def _patient(args: argparse.Namespace, pad: SensorEmulator, stop: threading.Event) -> None:
    from services.common.bus import Bus
    from services.intent.patient import SimulatedPatient

    patient = SimulatedPatient(pad, args.patient_model, seed=args.seed)
    kind = "hurried: quick presses, E_big" if args.patient_model == 1 else "careful: held, E_small"
    print(f"simulated patient (M_{args.patient_model}, {kind}) answering decision requests")
    with Bus(_client_settings(args), "patient") as bus:
        patient.run(bus, stop)
    print(f"answered {patient.answered} requests")


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _model_arg(text: str) -> tuple[int, int]:
    try:
        return parse_model(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _reach(args: argparse.Namespace) -> int:
    from dammrl.runner import ReachRunner, ReachSettings
    from services.controller.config import ControllerSettings
    from services.sim.config import DomainRandomization, SimSettings

    controller: dict[str, object] = {}
    if args.ik:
        controller["ik_solver"] = args.ik
    if args.feedforward:
        controller["feedforward"] = args.feedforward
    sim = SimSettings(randomization=DomainRandomization(enabled=args.randomize))
    settings = ReachSettings(sim=sim, controller=ControllerSettings.model_validate(controller))
    runner = ReachRunner(settings)
    triggers = ["fixed", "event"] if args.trigger == "both" else [args.trigger]
    task = runner.sample(args.seed)
    results = [runner.run(args.seed, args.model, trigger=t, task=task) for t in triggers]
    if args.json:
        for result in results:
            print(json.dumps(result.summary()))
    else:
        print(_table([r.summary() for r in results]))
    if args.plot:
        from dammrl.plots import plot_reaches

        path = plot_reaches(results, runner.settings.task.goal_tolerance_m, args.plot)
        print(f"figure written to {path}", file=sys.stderr)
    return 0


def _up(args: argparse.Namespace) -> int:
    from dammrl.launch import Stack, StackOptions

    options = StackOptions(
        mode=args.mode, episodes=args.episodes, seed=args.seed, model=args.model,
        trigger=args.trigger, port=args.bus_port, namespace=args.namespace, json=args.json,
        serial_port=args.port,
        calibration=args.calibration,
        record=args.record,
    )  # fmt: skip
    return Stack(options, out=_print, info=_print_err).run()


def _print(line: str) -> None:
    print(line, flush=True)


def _print_err(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _client_settings(args: argparse.Namespace) -> BusSettings:
    from services.common.config import BusSettings

    return BusSettings(connect=args.connect or ["tcp/127.0.0.1:7447"], namespace=args.namespace)


def _status(args: argparse.Namespace) -> int:
    from dammrl.inspect import status

    print(status(_client_settings(args)))
    return 0


def _echo(args: argparse.Namespace) -> int:
    from dammrl.inspect import echo

    echo(_client_settings(args), args.topic, hz=args.hz, count=args.count, duration_s=args.duration)
    return 0


def _schemas(args: argparse.Namespace) -> int:
    from schemas import TOPICS

    args.out.mkdir(parents=True, exist_ok=True)
    for topic, message_type in TOPICS.items():
        path = args.out / f"{message_type.__name__}.json"
        schema = message_type.model_json_schema() | {"x-dammrl-topic": topic}
        path.write_text(json.dumps(schema, indent=2) + "\n")
        print(f"{topic:16s} -> {path}")
    return 0


UNITS = {"t_total_s": "s", "t_step_mean_s": "s", "final_error_m": "m", "jerk_isj": "m^2/s^5"}


def _table(rows: list[dict[str, object]]) -> str:
    """Metrics as aligned text, one column per reach."""
    keys = [k for k in rows[0] if k not in ("start_m", "goal_m")] + ["start_m", "goal_m"]
    header = ["metric"] + [str(r["trigger"]) for r in rows]
    lines = [[f"{k} [{UNITS[k]}]" if k in UNITS else k] + [_fmt(r[k]) for r in rows] for k in keys]
    widths = [max(len(line[c]) for line in [header, *lines]) for c in range(len(header))]
    out = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))]
    out.append("  ".join("-" * w for w in widths))
    out += ["  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)) for line in lines]
    return "\n".join(out)


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    return str(value)


if __name__ == "__main__":
    raise SystemExit(main())
