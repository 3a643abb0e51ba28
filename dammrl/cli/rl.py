"""The dual-agent DQN: ``dammrl train`` and ``dammrl evaluate``."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any

from dammrl.cli.common import SEEDS_HELP, Commands, output_dir, progress_bar, seeds_arg


def register(commands: Commands) -> None:
    """Add ``train``, ``frontier`` and ``evaluate``."""
    train = commands.add_parser("train", help="train the dual-agent DQN (DAMMRL)")
    train.add_argument("--reward", type=int, choices=[1, 2], required=True,
                       help="1: accuracy focus (beta = 0); 2: speed and accuracy")  # fmt: skip
    train.add_argument("--out", type=output_dir, required=True,
                       help="run directory (resumes if present)")  # fmt: skip
    train.add_argument("--episodes", type=int, help="default 1500 (DAMMRL_RL_EPISODES)")
    train.add_argument("--seed", type=int, help="the run's seed (one run; default 0)")
    train.add_argument("--seeds", type=int, metavar="N",
                       help="train N seeds (0..N-1) into OUT/seed-K in parallel, evaluate each "
                       "on held-out seeds and aggregate (summary.md, curves.png)")  # fmt: skip
    train.add_argument("--ship", type=output_dir, metavar="DIR",
                       help="with --seeds: copy the best run on the validation seeds to DIR "
                       "(checkpoint, curves, TensorBoard log, every seed's results)")  # fmt: skip
    train.add_argument("--ship-seeds", type=output_dir, metavar="DIR",
                       help="with --seeds: copy every run to DIR/seed-K as a study reads them "
                       "(greedy networks, training log, settings, evaluation; e.g. "
                       "dammrl_core/policies/reward1/seeds)")  # fmt: skip
    train.add_argument("--beta", type=float, help="the time weight (default: the reward's)")
    train.add_argument("--no-randomize", dest="randomize", action="store_false",
                       help="train on the nominal arm (default: randomised arms, S1)")  # fmt: skip
    train.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                       help="where the networks learn (auto: a GPU when present)")  # fmt: skip
    _grid_options(train)
    train.set_defaults(handler=_train)
    frontier = commands.add_parser(
        "frontier", help="the reward-weight frontier: a grid of time weights, several seeds each"
    )
    frontier.add_argument("--out", type=output_dir, required=True, help="grid directory")
    frontier.add_argument("--betas", type=_betas, default=[0.0, 0.25, 0.5, 1.0, 2.0, 4.0],
                          help="time weights, comma-separated (default 0,0.25,0.5,1,2,4; 0 is "
                          "Reward 1, 1 is Reward 2)")  # fmt: skip
    frontier.add_argument("--seeds", type=int, default=3, metavar="N", help="seeds per weight")
    frontier.add_argument("--episodes", type=int, default=1500, help="episodes per run")
    _grid_options(frontier)
    frontier.set_defaults(handler=_frontier)
    evaluate = commands.add_parser("evaluate", help="greedy evaluation of a trained run")
    evaluate.add_argument(
        "--checkpoint",
        type=Path,
        required=True,
        help="run directory, .pt or shipped policy (reward1, reward2)",
    )
    evaluate.add_argument("--seeds", default="100", metavar="N|A:B", type=seeds_arg,
                          help=SEEDS_HELP)  # fmt: skip
    evaluate.add_argument("--randomize", action="store_true", help="on randomised arms")
    evaluate.add_argument("--json", action="store_true", help="one JSON object")
    evaluate.add_argument("--adaptive", action="store_true",
                          help="inside the adaptive mode: the seeds in order as one session, "
                          "re-selecting when DAMMRL_POLICY_TARGETS__* are missed")  # fmt: skip
    evaluate.set_defaults(handler=_evaluate)


def _grid_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--eval-seeds", default="100", metavar="N|A:B", type=seeds_arg,
                        help="held-out seeds each run is evaluated on; " + SEEDS_HELP)  # fmt: skip
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                        help="training processes here (default: every core)")  # fmt: skip
    parser.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                        help="run on a Ray cluster (no address: a local Ray instance)")  # fmt: skip


def _betas(text: str) -> list[float]:
    try:
        values = [float(part) for part in text.split(",") if part.strip()]
    except ValueError:
        values = []
    if not values or any(not 0 <= v < 1000 for v in values) or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(
            f"expected distinct weights >= 0 like 0,0.5,1; got {text!r}"
        )
    return sorted(values)


def _train(args: argparse.Namespace) -> int:
    """Train (or resume) a run; progress on stderr, the last 50 episodes' success at the end."""
    from dammrl.learning.rl.config import RewardWeights, TrainSettings
    from dammrl.learning.rl.train import EpisodeLog, progress_summary, train
    from dammrl_core.errors import UsageError

    if args.seeds is not None:
        return _train_seeds(args)
    if args.ship is not None:
        raise UsageError("--ship needs --seeds (it picks the best of several runs)")
    if args.ship_seeds is not None:
        raise UsageError("--ship-seeds needs --seeds (it ships every run of them)")
    overrides = {k: v for k in ("episodes", "seed") if (v := getattr(args, k)) is not None}
    settings = TrainSettings(**overrides, randomize=args.randomize)
    weights = RewardWeights.preset(args.reward)
    if args.beta is not None:
        weights = weights.model_copy(update={"beta": args.beta})
    update, close = progress_bar(settings.episodes, f"Reward {args.reward}", unit="episode")
    done = 0

    def on_episode(logs: list[EpisodeLog]) -> None:
        nonlocal done
        update(len(logs) - done, progress_summary(logs))
        done = len(logs)

    try:
        logs = train(args.reward, args.out, settings, args.device, on_episode, weights)
    finally:
        close()
    recent = logs[-50:]
    print(f"trained {len(logs)} episodes; last 50: success "
          f"{sum(r.success for r in recent) / len(recent):.0%}; run in {args.out}")  # fmt: skip
    return 0


def _train_seeds(args: argparse.Namespace) -> int:
    from dammrl.study.training import (
        check_seeds,
        group_jobs,
        ship,
        ship_seeds,
        write_group_report,
    )
    from dammrl_core.errors import UsageError

    if not 1 <= args.seeds <= 70 or args.seed is not None:
        raise UsageError("--seeds N takes 1 to 70 seeds (0..N-1), and no --seed")
    check_seeds(args.eval_seeds)
    episodes = args.episodes or 1500
    jobs = group_jobs(args.out, args.reward, args.seeds, episodes, args.eval_seeds, args.beta,
                      args.randomize)  # fmt: skip
    wall_s = _run_grid(jobs, args)
    print(write_group_report(args.out, f"Reward {args.reward}", _command(), wall_s))
    if args.ship is not None:
        print(f"shipped seed-{ship(args.out, args.ship)} to {args.ship}")
    if args.ship_seeds is not None:
        seeds = ship_seeds(args.out, args.ship_seeds)
        print(f"shipped {len(seeds)} runs (seed-0 ... seed-{seeds[-1]}) to {args.ship_seeds}")
    return 0


def _frontier(args: argparse.Namespace) -> int:
    from dammrl.study.frontier import frontier_jobs, write_report
    from dammrl.study.training import check_seeds

    check_seeds(args.eval_seeds)
    jobs = frontier_jobs(args.out, args.betas, args.seeds, args.episodes, args.eval_seeds)
    wall_s = _run_grid(jobs, args)
    print(write_report(args.out, args.betas, _command(), wall_s))
    return 0


def _run_grid(jobs: list[Any], args: argparse.Namespace) -> float:
    """Train and evaluate every job (processes or Ray) with a progress bar; wall time [s]."""
    from dammrl.study.training import run_training
    from dammrl_core.errors import UsageError

    if args.jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {args.jobs}")
    started = time.monotonic()
    update, close = progress_bar(len(jobs), "training runs", unit="run")
    try:
        run_training(jobs, args.jobs, args.ray, update)
    finally:
        close()
    return time.monotonic() - started


def _command() -> str:
    return "dammrl " + shlex.join(sys.argv[1:])


def _evaluate(args: argparse.Namespace) -> int:
    """Greedy episodes of a trained run; their metrics as a table or one JSON object."""
    from dammrl.learning.rl.train import evaluate

    update, close = progress_bar(len(args.seeds), "greedy reaches")
    try:
        result = evaluate(args.checkpoint, args.seeds, args.randomize, lambda: update(1),
                          args.adaptive)  # fmt: skip
    finally:
        close()
    if args.json:
        print(json.dumps(result))
    else:
        print(evaluation_table(result))
    return 0


EVALUATION_ROWS = {  # key: (label, scale, format, unit)
    "success_rate": ("success", 100, ".0f", "%"),
    "t_total_s": ("t_total (mean)", 1, ".2f", "s"),
    "final_error_m": ("final error (mean)", 1000, ".1f", "mm"),
    "n_osc": ("N_osc (mean)", 1, ".1f", "reversals"),
    "share_e_small": ("decisions with E_small", 100, ".0f", "%"),
    "share_all_small_steps": ("decisions with all-small steps", 100, ".0f", "%"),
}


def evaluation_table(result: dict[str, Any]) -> str:
    """``dammrl evaluate``'s figures, rounded and with their units."""
    lines = [f"{'checkpoint':32s} {result['checkpoint']}",
             f"{'reward':32s} {result['reward']}",
             f"{'held-out seeds':32s} {result['seeds']} ({result['episodes']} reaches, "
             f"{'randomised' if result['randomize'] else 'nominal'} arm)"]  # fmt: skip
    for key, (label, scale, spec, unit) in EVALUATION_ROWS.items():
        lines.append(f"{label:32s} {result[key] * scale:{spec}} {unit}")
    if result.get("adaptive"):
        lines.append(f"{'switches (adaptive mode)':32s} {len(result['switches'])}")
        lines += [f"  {switch}" for switch in result["switches"]]
    return "\n".join(lines)
