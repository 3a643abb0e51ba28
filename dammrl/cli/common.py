"""What the command groups share: argument types, the bus flags, printing, the metrics table."""

from __future__ import annotations

import argparse
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

from schemas import DEFAULT_NAMESPACE

if TYPE_CHECKING:
    from services.common.config import BusSettings
    from services.common.runs import RunCard

Commands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"
"""The ``COMMAND`` (or ``ACTION``) subparsers a group adds its parsers to."""

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
"""Where a client looks for the stack: the default endpoint of ``dammrl up``."""
CONNECT_HELP = ("where the stack listens, e.g. tls/10.0.0.5:7447 (default: the local `dammrl up` "
                f"there is, over tls with its credentials; else {DEFAULT_CONNECT})")  # fmt: skip


UNITS = {"t_total_s": "s", "t_step_mean_s": "s", "final_error_m": "m", "jerk_isj": "m^2/s^5"}


def positive(text: str) -> float:
    """Argument type: a finite number above zero."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
"""What a figure can be written as (matplotlib's formats chosen by the name)."""


def output_file(*suffixes: str) -> Callable[[str], Path]:
    """Argument type: a file to write, its name ending in one of ``suffixes`` (any when
    none), in a directory that exists and may be written: refused before any work."""

    def convert(text: str) -> Path:
        path = Path(text)
        if suffixes and path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{text}: the name must end in {', '.join(suffixes)}")
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{text} is a directory, not a file")
        _check_writable(path.parent)
        return path

    convert.__name__ = "output file"  # argparse names the type in its errors
    return convert


def output_dir(text: str) -> Path:
    """Argument type: a directory to write into (made if missing, with its parents)."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} exists and is not a directory")
    existing = next(p for p in (path, *path.parents) if p.exists() or p == Path("."))
    _check_writable(existing)
    return path


def _check_writable(directory: Path) -> None:
    import os

    directory = directory if str(directory) else Path(".")
    if not directory.is_dir():
        raise argparse.ArgumentTypeError(f"no such directory: {directory}")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot write in {directory} (permission denied)")


SEEDS_HELP = (
    "held-out task seeds: N (the first N, default 100) or A:B (seeds A to B-1, all >= "
    "7,000,000: training never uses them)"
)


def seeds_arg(text: str) -> range:
    """Argument type: held-out task seeds ``N`` or ``A:B``."""
    from dammrl_core.task import held_out_seeds

    try:
        return held_out_seeds(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def model_arg(text: str) -> tuple[int, int]:
    """Argument type: a multi-model index ``I,J``."""
    from dammrl_core.models import parse_model

    try:
        return parse_model(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


CREDENTIALS_HELP = (
    "folder from `dammrl bus init`: join a secured stack over mutual TLS "
    "(also DAMMRL_BUS_CREDENTIALS)"
)


BUS_PORT_HELP = "the loopback port of a local `dammrl up --bus-port N` (its credentials are found)"


def add_bus_arguments(parser: argparse.ArgumentParser, connect_help: str) -> None:
    """``--connect``, ``--bus-port``, ``--namespace`` and ``--credentials``: where and how
    a client finds the stack (none of them: the local run there is, see ``bus_settings``)."""
    add_connect(parser, connect_help)
    parser.add_argument("--bus-port", type=int, metavar="N", help=BUS_PORT_HELP)
    parser.add_argument("--namespace", help="the stack's key prefix (default: the run's, or "
                        f"{DEFAULT_NAMESPACE})")  # fmt: skip
    add_credentials(parser)


def add_credentials(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--credentials", type=Path, metavar="DIR", help=CREDENTIALS_HELP)


def add_connect(parser: argparse.ArgumentParser, helptext: str) -> None:
    """``--connect ENDPOINT``, repeatable; none means ``DEFAULT_CONNECT``."""
    parser.add_argument("--connect", action="append", metavar="ENDPOINT", help=helptext)


def bus_settings(
    args: argparse.Namespace,
    namespace: str | None = None,
    beside: Callable[[], RunCard | None] | None = None,
) -> BusSettings:
    """A client's bus settings from the flags (``--connect``, ``--bus-port``), else the
    environment's; where none says where, the local run ``beside`` finds (an emulator:
    the run that reads it; by default: the only local run), else ``DEFAULT_CONNECT``.
    ``namespace`` if ``--namespace`` is unset (else the run's, else the default)."""
    from services.common.config import BusSettings
    from services.common.runs import local_runs, only_run

    environment = BusSettings()  # DAMMRL_BUS_* where the flags are silent
    credentials = getattr(args, "credentials", None) or environment.credentials
    connect = _endpoints(args) or list(environment.connect)
    if not connect:
        found = (beside or only_run)()
        connect = [found.endpoint] if found is not None else [DEFAULT_CONNECT]
    cards = {run.port: run for run in local_runs()}  # a local run there: its namespace too
    run = next((cards[p] for p in map(_loopback_port, connect) if p in cards), None)
    if credentials is None:  # a local `dammrl up` on that port: its own credentials
        credentials = _local_stack_credentials(connect, cards)
    if credentials is not None:  # a secured stack speaks TLS only
        connect = [e.replace("tcp/", "tls/", 1) if e.startswith("tcp/") else e for e in connect]
    else:
        _refuse_tls_without_credentials(connect)
    run_namespace = None if run is None else run.namespace
    chosen = getattr(args, "namespace", None) or namespace or run_namespace or DEFAULT_NAMESPACE
    return BusSettings(connect=connect, namespace=chosen, credentials=credentials)


def _endpoints(args: argparse.Namespace) -> list[str]:
    """The endpoints the flags name (``--connect`` or ``--bus-port``, not both)."""
    from dammrl_core.errors import UsageError

    connect, port = getattr(args, "connect", None), getattr(args, "bus_port", None)
    if connect and port is not None:
        raise UsageError("--connect and --bus-port both say where the stack is: one of them")
    if port is not None:
        if not 0 < port < 65_536:
            raise UsageError(f"--bus-port {port}: a TCP port, 1-65535")
        return [f"tcp/127.0.0.1:{port}"]
    return list(connect or [])


def bus_settings_found_later(args: argparse.Namespace) -> Callable[[], BusSettings] | None:
    """For a client that may start before its stack: the bus settings looked up again
    (a local `dammrl up` started since, or started again, has its own credentials), or
    None when the user named the credentials (nothing to find)."""
    from services.common.config import BusSettings

    if getattr(args, "credentials", None) or BusSettings().credentials:
        return None
    return lambda: bus_settings(args)


LOOPBACK = ("127.0.0.1", "localhost", "[::1]")


def _loopback_port(endpoint: str) -> int | None:
    _, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    return int(port) if host in LOOPBACK and port.isdigit() else None


def _local_stack_credentials(endpoints: list[str], cards: dict[int, RunCard]) -> Path | None:
    """The credentials of the `dammrl up` this machine runs on one of ``endpoints``' ports
    (loopback endpoints only), if there is one: its card's (a lab's, or its own), or its
    own folder."""
    from services.common.security import CA_FILE, run_credentials, stale_run_credentials

    for endpoint in endpoints:
        port = _loopback_port(endpoint)
        if port is None:
            continue
        card = cards.get(port)
        if card is not None and card.credentials is not None:
            return Path(card.credentials)
        folder = run_credentials(port)
        if stale_run_credentials(folder):  # its launcher is gone: useless, removed
            shutil.rmtree(folder, ignore_errors=True)
        if (folder / CA_FILE).is_file():
            return folder
    return None


def _refuse_tls_without_credentials(endpoints: list[str]) -> None:
    """A secured endpoint and no credentials found: say where a run's would be."""
    from services.common.security import CredentialsError, run_credentials

    for endpoint in (e for e in endpoints if e.startswith("tls/")):
        port = _loopback_port(endpoint)
        local = "" if port is None else (
            f"a `dammrl up --bus-port {port}` of yours keeps its own in "
            f"{run_credentials(port, create=False)} while it runs (is it running, as this "
            "user?); ")  # fmt: skip
        raise CredentialsError(f"{endpoint} is a secured stack's and no credentials were found: "
                               f"{local}a lab's stack: --credentials DIR (or "
                               "DAMMRL_BUS_CREDENTIALS)")  # fmt: skip


def print_out(line: str) -> None:
    """One line of results on stdout, at once (a pipe sees it live)."""
    print(line, flush=True)


def print_err(line: str) -> None:
    """One line of progress on stderr, at once."""
    print(line, file=sys.stderr, flush=True)


def table(rows: list[dict[str, object]]) -> str:
    """Metrics as aligned text, one column per reach."""
    keys = [k for k in rows[0] if k not in ("start_m", "goal_m")] + ["start_m", "goal_m"]
    header = ["metric"] + [str(r["trigger"]) for r in rows]
    lines = [[f"{k} [{UNITS[k]}]" if k in UNITS else k] + [fmt(r[k]) for r in rows] for k in keys]
    return aligned(header, lines)


def table_of_rows(rows: list[dict[str, object]]) -> str:
    """Rows as aligned text, one column per key (the first row's)."""
    header = list(rows[0])
    return aligned(header, [[str(r.get(k, "")) for k in header] for r in rows])


def aligned(header: list[str], lines: list[list[str]]) -> str:
    """A header, a rule and lines, their columns aligned."""
    widths = [max(len(line[c]) for line in [header, *lines]) for c in range(len(header))]
    out = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))]
    out.append("  ".join("-" * w for w in widths))
    out += ["  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)) for line in lines]
    return "\n".join(out)


def fmt(value: object) -> str:
    """A metric for the table: floats to 4 significant digits, lists as tuples."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "(" + ", ".join(fmt(v) for v in value) + ")"
    return str(value)


def progress_bar(
    total: int | None, description: str, unit: str = "reach"
) -> tuple[Callable[..., None], Callable[[], None]]:
    """Progress on stderr: a bar with ETA on a terminal (tqdm), else a plain line every
    10 % or 30 s (a log file or a CI job sees it move): ``update(n, postfix=None)`` and
    ``close()``."""
    if not sys.stderr.isatty():
        return _progress_lines(total, description, unit)
    from tqdm import tqdm

    bar = tqdm(total=total, desc=description, unit=unit, file=sys.stderr, dynamic_ncols=True)

    def update(n: int, postfix: str | None = None) -> None:
        if postfix is not None:
            bar.set_postfix_str(postfix, refresh=False)
        bar.update(n)

    return update, bar.close


def _progress_lines(
    total: int | None, description: str, unit: str, every_s: float = 30.0, quiet_s: float = 5.0
) -> tuple[Callable[..., None], Callable[[], None]]:
    """Plain progress lines, none for a job done within ``quiet_s``."""
    import time

    started = time.monotonic()
    plural = unit + ("es" if unit.endswith(("ch", "sh", "s", "x")) else "s")
    done, said_at, said_tenth, said = 0, started, 0, False

    def line(postfix: str | None) -> str:
        elapsed = time.monotonic() - started
        of = f"/{total}" if total else ""
        eta = f", ~{elapsed / done * (total - done):.0f} s left" if total and done else ""
        tail = f" ({postfix})" if postfix else ""
        return f"{description}: {done}{of} {plural} in {elapsed:.0f} s{eta}{tail}"

    def update(n: int, postfix: str | None = None) -> None:
        nonlocal done, said_at, said_tenth, said
        done += n
        now = time.monotonic()
        tenth = 10 * done // total if total else 0
        if now - started >= quiet_s and (tenth > said_tenth or now - said_at >= every_s):
            said_at, said_tenth, said = now, tenth, True
            print(line(postfix), file=sys.stderr, flush=True)

    def close() -> None:
        if said and said_tenth < 10:
            print(line(None), file=sys.stderr, flush=True)

    return update, close


def headless_gl() -> None:
    """Choose MuJoCo's offscreen OpenGL before MuJoCo is imported: on Linux without a
    display, EGL (GPU or Mesa) or else OSMesa, whichever library is installed. A choice in
    ``MUJOCO_GL`` is kept."""
    import ctypes.util
    import os

    if "MUJOCO_GL" in os.environ or sys.platform != "linux":
        return
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return
    for backend, library in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(library):
            os.environ["MUJOCO_GL"] = backend
            return


def check_video_path(path: Path) -> None:
    """A video's name says its format; MP4 needs PyAV (the ``video`` extra)."""
    import importlib.util

    from dammrl_core.errors import UsageError

    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise UsageError(f"video {path}: the name must end in .mp4 or .gif")
    if suffix == ".mp4" and importlib.util.find_spec("av") is None:
        raise UsageError("MP4 needs PyAV: pip install 'dammrl[video]' (or write a .gif)")


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` with its noun in the number it takes: 1 participant, 2 participants."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def display_port(text: str) -> int:
    """A TCP port for the participant display (1-65535)."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: a port is a whole number 1-65535")
    return port


def outcome_seconds(text: str) -> float:
    """How long a reach's outcome stays on the display (0-30 s, the controller's range)."""
    from dammrl.people.session_steps import MAX_OUTCOME_S

    try:
        seconds = float(text)
    except ValueError:
        seconds = -1.0
    if not 0.0 <= seconds <= MAX_OUTCOME_S:  # (NaN fails too)
        raise argparse.ArgumentTypeError(
            f"{text!r}: the outcome is held 0 to {MAX_OUTCOME_S:g} s")  # fmt: skip
    return seconds
