"""The runs of ``dammrl up`` on this machine, as the tools beside them find them: while it
runs, each leaves a card in the user's private runtime folder with its port, endpoint,
namespace, credentials and the person's input (the pad's device, the wearable's stream).
An emulated pad or armband joins the run that reads it, a tool the only run there is,
whatever port it was given; a card whose launcher is gone (``kill -9``) is ignored and
removed by whoever finds it."""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

from services.common.security import private_folder


@dataclass(frozen=True)
class RunCard:
    """What a tool needs to join one local run."""

    pid: int  # the launcher's
    port: int
    endpoint: str  # tls/127.0.0.1:PORT, or tcp/ for an --insecure run
    namespace: str
    credentials: str | None  # the run's folder (its own, or a lab's)
    pad_port: str | None = None  # the pressure pad's device, as an absolute path
    lsl_stream: str | None = None  # the wearable's LSL stream


def card_path(port: int, create: bool = True) -> Path:
    return private_folder(create) / f"run-{port}.json"


def write_card(card: RunCard) -> Path:
    """Leave ``card`` for the tools (replacing a card of an earlier run on that port)."""
    path = card_path(card.port)
    partial = path.with_suffix(".partial")
    partial.write_text(json.dumps(asdict(card)))
    os.replace(partial, path)  # whole or absent: a reader never meets half a card
    return path


def remove_card(port: int, pid: int) -> None:
    """Remove the card of the run on ``port`` if it is the one of launcher ``pid``."""
    path = card_path(port, create=False)
    card = _read(path)
    if card is not None and card.pid == pid:
        path.unlink(missing_ok=True)


def local_runs() -> list[RunCard]:
    """The runs of this user that are up, by port (stale cards removed)."""
    folder = private_folder(create=False)
    runs = []
    for path in sorted(folder.glob("run-*.json")) if folder.is_dir() else []:
        card = _read(path)
        if card is None:
            continue
        if _alive(card.pid):
            runs.append(card)
        else:
            path.unlink(missing_ok=True)
    return sorted(runs, key=lambda r: r.port)


def run_reading(pad_link: Path | None = None, stream: str | None = None) -> RunCard | None:
    """The local run whose person's input is the pad at ``pad_link`` or the LSL
    ``stream`` (the one started beside an emulator of it), if one is up."""
    for card in local_runs():
        if pad_link is not None and card.pad_port and _same_file(pad_link, card.pad_port):
            return card
        if stream is not None and card.lsl_stream == stream:
            return card
    return None


def only_run() -> RunCard | None:
    """The one local run, if exactly one is up."""
    runs = local_runs()
    return runs[0] if len(runs) == 1 else None


def _read(path: Path) -> RunCard | None:
    try:
        return RunCard(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's (never in our private folder)
        return True
    return True


def _same_file(link: Path, device: str) -> bool:
    """Whether the emulator's ``link`` is the run's ``device`` (one path, or the same
    pseudo-terminal behind two)."""
    if os.path.abspath(link) == os.path.abspath(device):
        return True
    with contextlib.suppress(OSError):
        return os.path.samefile(link, device)
    return False
