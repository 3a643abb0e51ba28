"""``dammrl bus``: credentials for a secured bus."""

from __future__ import annotations

import argparse
from pathlib import Path

from dammrl.cli.common import Commands, print_err, print_out
from dammrl_core.errors import Exit


def register(commands: Commands) -> None:
    bus = commands.add_parser("bus", help="credentials for a secured bus (mutual TLS, ACL)")
    actions = bus.add_subparsers(dest="action", required=True, metavar="ACTION")
    helptext = (
        "create a lab CA and one certificate per role: each service's, and observer "
        "(read only), display (a comfort rating), operator (stop, release, session)"
    )
    init = actions.add_parser("init", help=helptext, description=helptext)
    init.add_argument("--out", type=Path, required=True, metavar="DIR",
                      help="folder to create (keys readable by you only)")  # fmt: skip
    init.add_argument("--host", action="append", default=[], metavar="NAME_OR_IP",
                      help="an address the services listen on, for separate machines "
                           "(repeatable; localhost and 127.0.0.1 are always in)")  # fmt: skip
    init.set_defaults(handler=_init)


def _init(args: argparse.Namespace) -> int:
    from services.common.certificates import create_credentials
    from services.common.security import ROLES

    if args.out.exists() and any(args.out.iterdir()):
        print_err(f"dammrl: error: {args.out} is not empty; choose a new folder")
        return Exit.BAD_INPUT
    create_credentials(args.out, args.host)
    print_out(f"credentials for {', '.join(ROLES)} in {args.out}")
    print_out(f"every service and tool: DAMMRL_BUS_CREDENTIALS={args.out.resolve()} and tls/ "
              "endpoints; give each machine only ca.pem and the roles it runs: a service its "
              "name, a viewer 'observer' (reads), the participant's display 'display' (their "
              "comfort rating), the therapist's PC 'operator' (dammrl stop and its release, "
              "dammrl up, the session console)")  # fmt: skip
    return 0
