"""The dual-agent DQN: ``dammrl train`` and ``dammrl evaluate``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dammrl.cli.common import SEEDS_HELP, Commands, print_err, seeds_arg


def register(commands: Commands) -> None:
    """Add ``train`` and ``evaluate``."""
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
    evaluate.add_argument("--seeds", default="100", metavar="N|A:B", type=seeds_arg,
                          help=SEEDS_HELP)  # fmt: skip
    evaluate.add_argument("--json", action="store_true")
    evaluate.set_defaults(handler=_evaluate)


def _train(args: argparse.Namespace) -> int:
    """Train (or resume) a run; progress on stderr, the last 50 episodes' success at the end."""
    from dammrl.rl.config import TrainSettings
    from dammrl.rl.train import train

    overrides = {k: v for k in ("episodes", "seed") if (v := getattr(args, k)) is not None}
    settings = TrainSettings(**overrides)
    logs = train(args.reward, args.out, settings, args.device, progress=print_err)
    recent = logs[-50:]
    print(f"trained {len(logs)} episodes; last 50: success "
          f"{sum(r.success for r in recent) / len(recent):.0%}; run in {args.out}")  # fmt: skip
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    """Greedy episodes of a trained run; their metrics as text or one JSON object."""
    from dammrl.rl.train import evaluate

    result = evaluate(args.checkpoint, args.seeds)
    if args.json:
        print(json.dumps(result))
    else:
        print("\n".join(f"{k:22s} {v}" for k, v in result.items()))
    return 0
