"""The ``dammrl`` command: the researcher's front door.

One module per command group, each with a ``register(commands)`` that adds its parsers
and their handlers; this module builds the parser and turns errors into exit codes.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import shtab
from pydantic import ValidationError

from dammrl import __version__
from dammrl.cli import (
    bus,
    coadapt,
    intent,
    reach,
    recording,
    rl,
    robot,
    sensor,
    session,
    settings,
    stack,
    study,
    view,
)
from dammrl_core.errors import EXIT_CODES_HELP, DammrlError, Exit
from dammrl_core.settings import error_line

GROUPS = (
    reach.register,
    stack.register,
    session.register,
    recording.register,
    intent.register,
    sensor.register,
    robot.register,
    rl.register,
    study.register,
    coadapt.register,
    coadapt.register_adapt,
    view.register,
    bus.register,
    settings.register,
    robot.register_stop,
    stack.register_schemas,
)
"""In the order of ``dammrl --help``."""


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; its exit code (``Exit``): a bad setting, file or device is one
    line on stderr."""
    try:
        args = parser().parse_args(argv)  # --help, --print-completion: may meet a closed pipe
        return int(args.handler(args))
    except BrokenPipeError:  # `dammrl echo ... | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return Exit.OK
    except (DammrlError, ValidationError, OSError) as exc:  # OSError: a path or device
        print(f"dammrl: error: {error_line(exc)}", file=sys.stderr)
        return exc.exit_code if isinstance(exc, DammrlError) else Exit.BAD_INPUT
    except KeyboardInterrupt:
        print("dammrl: interrupted", file=sys.stderr)
        return Exit.INTERRUPTED


def parser() -> argparse.ArgumentParser:
    """The ``dammrl`` parser with every command group."""
    top = argparse.ArgumentParser(
        prog="dammrl",
        description="Event-triggered human-robot co-adaptation (DAMMRL).",
        epilog=EXIT_CODES_HELP,
    )
    top.add_argument("--version", action="version", version=f"dammrl {__version__}")
    shtab.add_argument_to(top, ["--print-completion"], help="print a shell completion script "
                          "(bash, zsh, tcsh, fish or powershell), e.g. dammrl "
                          "--print-completion bash > /etc/bash_completion.d/dammrl")  # fmt: skip
    commands = top.add_subparsers(required=True, metavar="COMMAND")
    for register in GROUPS:
        register(commands)
    _with_exit_codes(commands)
    return top


def _with_exit_codes(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Every command's ``--help`` ends with the exit codes (nested actions included)."""
    unique = {id(parser): parser for parser in commands.choices.values()}  # aliases: once
    for command in unique.values():
        command.epilog = (
            f"{command.epilog}\n\n{EXIT_CODES_HELP}" if command.epilog else EXIT_CODES_HELP
        )
        for action in command._actions:
            if isinstance(action, argparse._SubParsersAction):
                _with_exit_codes(action)
