"""The ``dammrl`` command: the researcher's front door.

One module per command group, each with a ``register(commands)`` that adds its parsers
and their handlers; this module builds the parser and turns errors into exit codes.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence

from dammrl import __version__
from dammrl_core.errors import EXIT_CODES_HELP, DammrlError, Exit

GROUPS = (
    "reach",
    "stack",
    "session",
    "recording",
    "intent",
    "sensor",
    "robot",
    "rl",
    "study",
    "coadapt",
    "coadapt:register_adapt",
    "view",
    "bus",
    "settings",
    "stop",
    "stack:register_schemas",
)
"""The modules of ``dammrl.cli`` whose ``register`` (or the function named after the colon)
adds their commands, in the order of ``dammrl --help``."""

QUICK = {"stop": "stop", "status": "stack"}
"""Commands an operator needs at once on a busy PC, and their group: the parser is built
from that group alone, so that nothing of the other commands is imported (the whole CLI
took 1.2 s of imports on a quiet machine, 85 s at load 40)."""


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; its exit code (``Exit``): a bad setting, file or device is one
    line on stderr."""
    words = sys.argv[1:] if argv is None else list(argv)
    if argv is None and words[:1] == ["stop"]:
        _ahead_of_the_load()
    from pydantic import ValidationError

    from dammrl_core.settings import error_line

    try:
        command = QUICK.get(words[0]) if words else None
        top = parser((command,)) if command else parser()
        args = top.parse_args(words)  # --help, --print-completion: may meet a closed pipe
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


def _ahead_of_the_load() -> None:
    """``dammrl stop`` as a program: before it imports anything more, the arm loop's
    scheduling priority where allowed (root or CAP_SYS_NICE; else as it was)."""
    from services.common.runtime import prioritise

    prioritise(True)


def parser(groups: Sequence[str] = GROUPS) -> argparse.ArgumentParser:
    """The ``dammrl`` parser with every command group (or only ``groups``)."""
    top = argparse.ArgumentParser(
        prog="dammrl",
        description="Event-triggered human-robot co-adaptation (DAMMRL).",
        epilog=EXIT_CODES_HELP,
    )
    top.add_argument("--version", action="version", version=f"dammrl {__version__}")
    if groups == GROUPS:
        import shtab

        shtab.add_argument_to(top, ["--print-completion"],
                              help="print a shell completion script (bash, zsh, tcsh, fish "
                                   "or powershell), e.g. dammrl --print-completion bash > "
                                   "/etc/bash_completion.d/dammrl")  # fmt: skip
    commands = top.add_subparsers(required=True, metavar="COMMAND")
    for group in groups:
        _register(group)(commands)
    _with_exit_codes(commands)
    return top


def _register(group: str) -> Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], None]:
    """The function of ``dammrl.cli.<module>`` that adds a group's commands."""
    module, _, function = group.partition(":")
    register: Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], None] = getattr(
        importlib.import_module(f"dammrl.cli.{module}"), function or "register"
    )
    return register


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
