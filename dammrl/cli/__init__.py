"""The ``dammrl`` command: the researcher's front door.

One module per command group, each with a ``register(commands)`` that adds its parsers
and their handlers; this module builds the parser and turns errors into exit codes.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from pydantic import ValidationError

from dammrl.cli import bus, reach, recording, rl, sensor, stack
from dammrl.core.errors import DammrlError

GROUPS = (
    reach.register,
    stack.register,
    recording.register,
    sensor.register,
    rl.register,
    bus.register,
    stack.register_schemas,
)
"""In the order of ``dammrl --help``."""


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; its exit code, 2 for a one-line error (bad usage exits 2 too)."""
    args = parser().parse_args(argv)
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


def parser() -> argparse.ArgumentParser:
    """The ``dammrl`` parser with every command group."""
    top = argparse.ArgumentParser(
        prog="dammrl", description="Event-triggered human-robot co-adaptation (DAMMRL)."
    )
    commands = top.add_subparsers(required=True, metavar="COMMAND")
    for register in GROUPS:
        register(commands)
    return top
