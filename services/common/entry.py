"""The entry point every service shares: flags for the bus, settings from the environment."""

from __future__ import annotations

import argparse
import logging
import os
import threading
from collections.abc import Callable, Sequence
from typing import Protocol

from pydantic import ValidationError

from dammrl_core.errors import EXIT_CODES_HELP, DammrlError, Exit
from dammrl_core.settings import error_line
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.logs import setup_logging
from services.common.runtime import TIME_CRITICAL, exit_within, prioritise, stop_on_signals
from services.common.security import remove_run_credentials

EPILOG = """\
Every setting can also come from the environment: DAMMRL_BUS_* for the bus (MODE,
LISTEN and CONNECT as JSON lists, MULTICAST_SCOUTING, NAMESPACE) and the service's own
prefix ({prefixes}); see docs/reference/settings.md and the settings classes for names and units.

{exit_codes}
"""


class Node(Protocol):
    def run(self, stop: threading.Event) -> None: ...


def run_service(
    name: str,
    description: str,
    prefixes: str,
    build: Callable[[Bus, argparse.Namespace], Node],
    argv: Sequence[str] | None = None,
    add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
) -> int:
    """Parse the bus flags (and the service's own), open the session, build the node and
    run it until a signal."""
    parser = argparse.ArgumentParser(
        prog=f"python -m services.{name}",
        description=description,
        epilog=EPILOG.format(prefixes=prefixes, exit_codes=EXIT_CODES_HELP),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--mode", choices=["peer", "client", "router"], help="Zenoh mode")
    parser.add_argument(
        "--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447"
    )
    parser.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/10.0.0.2:7447"
    )
    parser.add_argument("--namespace", help="key-expression prefix (default dammrl)")
    if add_arguments is not None:
        add_arguments(parser)
    args = parser.parse_args(argv)
    log = setup_logging(name)
    overrides = {
        k: v for k in ("mode", "listen", "connect", "namespace") if (v := getattr(args, k))
    }
    stop = stop_on_signals()
    exit_within(stop)  # a main thread stuck in native code cannot make it linger
    settings: BusSettings | None = None
    try:
        settings = BusSettings(**overrides)
        if settings.launcher_pid is not None:
            follow_launcher(settings.launcher_pid, stop)
        if settings.realtime:
            log.info(prioritise(name in TIME_CRITICAL))
        with Bus(settings, name) as bus:
            node = build(bus, args)
            bus.declare_alive()
            log.info("up on namespace %r", settings.namespace)
            node.run(stop)
    except (ValidationError, DammrlError) as exc:
        log.error("cannot start: %s", error_line(exc))
        return Exit.BAD_INPUT
    finally:
        if settings is not None:
            _remove_an_orphaned_runs_credentials(settings)
    log.info("stopped")
    return Exit.OK


LAUNCHER_CHECK_S = 0.5
"""How often a service started by ``dammrl up`` checks that its launcher still runs."""


def follow_launcher(launcher_pid: int, stop: threading.Event) -> None:
    """Stop when the launcher is gone, even killed with -9 (the parent-death signal it
    asked for covers Linux; this covers a signal that never came)."""

    def watch() -> None:
        while not stop.wait(LAUNCHER_CHECK_S):
            if os.getppid() != launcher_pid:
                logging.getLogger("dammrl").error("the launcher (pid %d) is gone: stopping",
                                                  launcher_pid)  # fmt: skip
                stop.set()

    if os.getppid() != launcher_pid:
        stop.set()  # it died before we looked
    threading.Thread(target=watch, name="follow-launcher", daemon=True).start()


def _remove_an_orphaned_runs_credentials(settings: BusSettings) -> None:
    """The launcher removes its run's credentials when it ends; if it was killed, the
    last of its services does (any of them: the first to get here)."""
    pid, folder = settings.launcher_pid, settings.credentials
    if pid is not None and folder is not None and os.getppid() != pid:
        remove_run_credentials(folder, pid)
