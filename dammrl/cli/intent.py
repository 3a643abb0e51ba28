"""``dammrl intent sources``: the intent sources installed (built-in and from packages)."""

from __future__ import annotations

import argparse

from dammrl.cli.common import Commands, print_out
from dammrl_core.errors import Exit


def register(commands: Commands) -> None:
    """Add ``intent`` and its actions."""
    intent = commands.add_parser("intent", help="the human agent's decisions: sources")
    actions = intent.add_subparsers(required=True, metavar="ACTION")
    helptext = (
        "the intent sources installed (built-in and from packages); choose one with "
        "DAMMRL_INTENT_SOURCE"
    )
    sources = actions.add_parser("sources", help=helptext, description=helptext)
    sources.set_defaults(handler=_sources)


def _sources(args: argparse.Namespace) -> int:
    from dammrl_core.intent.source import source_plugins

    for name, origin in source_plugins().items():
        print_out(f"{name:16s} {origin}")
    return Exit.OK
