"""``dammrl reach``: one simulated reach in-process, no bus."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from dammrl.cli.common import (
    FIGURE_SUFFIXES,
    Commands,
    check_video_path,
    headless_gl,
    model_arg,
    output_file,
    print_err,
    progress_bar,
    table,
)

if TYPE_CHECKING:
    from dammrl.stack.runner import ReachResult, ReachSettings


def register(commands: Commands) -> None:
    """Add ``reach``."""
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
        type=model_arg,
        default=(1, 1),
        metavar="I,J",
        help="multi-model M_ij: I=1 E_big, I=2 E_small; J=1..8 step vector "
        "(J-1 in binary = large on x,y,z; 1 all-small, 8 all-large)",
    )
    reach.add_argument("--seed", type=int, default=0, help="seed of start/goal, human, latency")
    reach.add_argument("--json", action="store_true", help="one JSON object per reach")
    reach.add_argument("--plot", type=output_file(*FIGURE_SUFFIXES), metavar="PNG",
                       help="save a trajectory figure (.png, .pdf, .svg, .jpg)")  # fmt: skip
    reach.add_argument("--ik", choices=["pinocchio", "ikpy"], help="IK solver (default pinocchio)")
    reach.add_argument("--feedforward", choices=["inverse_dynamics", "resolved_acceleration"],
                       help="computed-torque feed-forward (default: the setting)")  # fmt: skip
    reach.add_argument("--randomize", action="store_true", help="seeded domain randomisation")
    reach.add_argument("--video", type=output_file(), metavar="MP4|GIF",
                       help="render the reach (offscreen; .mp4 needs dammrl[video]); with "
                       "--trigger both, one file per trigger")  # fmt: skip
    reach.set_defaults(handler=_reach)


def _reach(args: argparse.Namespace) -> int:
    """Run the reach once per trigger on the same sampled task; print metrics, maybe plot."""
    if args.video is not None:
        check_video_path(args.video)  # before the reach runs
        headless_gl()  # before MuJoCo is imported
    from dammrl.stack.runner import ReachRunner

    runner = ReachRunner(_settings(args))
    triggers = ["fixed", "event"] if args.trigger == "both" else [args.trigger]
    task = runner.sample(args.seed)
    results = [runner.run(args.seed, args.model, trigger=t, task=task) for t in triggers]
    if args.json:
        for result in results:
            print(json.dumps(result.summary()))
    else:
        print(table([r.summary() for r in results]))
    if args.plot:
        from dammrl.views.plots import plot_reaches
        from dammrl_core.task import scene_layout

        path = plot_reaches(results, runner.settings.task.goal_tolerance_m, args.plot,
                            scene_layout(runner.settings.task))  # fmt: skip
        print_err(f"figure written to {path}")
    if args.video:
        for result in results:
            write_video_of(result, _video_path(args.video, result.trigger, len(results) > 1))
    return 0


def _video_path(path: Path, trigger: str, several: bool) -> Path:
    return path.with_name(f"{path.stem}-{trigger}{path.suffix}") if several else path


def write_video_of(result: ReachResult, path: Path) -> None:
    from dammrl.views.video import VideoSettings, frame_times, track_of_reach, write_video

    track = track_of_reach(result)
    update, close = progress_bar(len(frame_times(track, VideoSettings())), "video", "frame")
    try:
        frames = write_video(track, path, progress=update)
    finally:
        close()
    print_err(f"video written to {path} ({frames} frames)")


def _settings(args: argparse.Namespace) -> ReachSettings:
    """The runner's settings from ``--ik``, ``--feedforward`` and ``--randomize``."""
    from dammrl.stack.runner import ReachSettings
    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.sim.settings import DomainRandomization, SimSettings

    controller: dict[str, object] = {}
    if args.ik:
        controller["ik_solver"] = args.ik
    if args.feedforward:
        controller["feedforward"] = args.feedforward
    sim = SimSettings(randomization=DomainRandomization(enabled=args.randomize))
    return ReachSettings(sim=sim, controller=ControllerSettings.model_validate(controller))
