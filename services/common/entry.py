"""The entry point every service shares: flags for the bus, settings from the environment."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol

from pydantic import ValidationError

from dammrl_core.errors import EXIT_CODES_HELP, DammrlError, Exit
from dammrl_core.settings import error_line
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.logs import setup_logging
from services.common.runtime import (
    TIME_CRITICAL,
    exit_within,
    freeze_startup_heap,
    prioritise,
    stop_on_signals,
)
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
            freeze_startup_heap()
            bus.declare_alive()
            log.info("up on namespace %r", settings.namespace)
            node.run(stop)
    except (ValidationError, DammrlError) as exc:
        log.error("cannot start: %s", error_line(exc))
        return Exit.BAD_INPUT
    finally:
        if settings is not None:
            _remove_an_orphaned_runs_credentials(settings, stop.signum == signal.SIGHUP)
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


LAUNCHER_END_S = 2.0
"""A service told of its launcher's death waits at most this long for the launcher's last
thread to end before it decides who removes the run's keys [s]."""


def _remove_an_orphaned_runs_credentials(settings: BusSettings, launcher_died: bool) -> None:
    """The launcher removes its run's credentials when it ends; if it was killed, its
    services do (any of them: the first to get here). ``launcher_died``: the parent-death
    signal (SIGHUP) stopped this service."""
    pid, folder = settings.launcher_pid, settings.credentials
    if pid is not None and folder is not None and launcher_gone(pid, launcher_died):
        remove_run_credentials(folder, pid)


def launcher_gone(launcher_pid: int, dying: bool) -> bool:
    """Whether the launcher has ended (this process is no longer its child). The
    parent-death signal comes as the launcher's thread that started this process ends;
    after ``kill -9`` its other threads end after it, and until the last has, the
    launcher is still this process's parent: a service that stopped fast and looked then
    kept the keys (4 of 6 runs). ``dying``: that signal came; wait for the end."""
    deadline = time.monotonic() + (LAUNCHER_END_S if dying else 0.0)
    while os.getppid() == launcher_pid:
        if time.monotonic() >= deadline:
            return False  # alive: it removes them itself when it ends
        time.sleep(0.005)
    return True
