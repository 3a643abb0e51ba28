"""A participant's folder and their sessions' folders: pseudonymous ids, the files a
sitting writes (append-only logs, each line on disk before the next step), and the
listing of every session under a root (``dammrl session list``).

    <root>/enrolment.jsonl                      who was enrolled, in order (their rows)
    <root>/<participant>/participant.json      id, Latin-square row, current calibration
    <root>/<participant>/ses-01/...            one sitting (see dammrl.people.session)
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from dammrl.people.enrolment import Ledger
from dammrl_core.errors import ConfigurationError, UsageError
from dammrl_core.protocol import PARTICIPANT_ID, Protocol, load_protocol, plan_trials


def check_participant(participant: str) -> str:
    """``participant`` if it is a pseudonymous id; a UsageError saying what is expected."""
    if not re.fullmatch(PARTICIPANT_ID, participant):  # match's $ lets a final newline in
        raise UsageError(
            f"participant {participant!r}: give a pseudonymous id such as P012 (1-4 letters, "
            "1-6 digits); names and other personal data are never stored"
        )
    return participant.upper()


def now_utc() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_json(path: Path, content: dict[str, Any]) -> None:
    """Replace ``path`` atomically (a crash leaves the old file or the new one)."""
    temporary = path.with_suffix(path.suffix + ".tmp")
    temporary.write_text(json.dumps(content, indent=2) + "\n")
    with open(temporary, "rb+") as handle:
        os.fsync(handle.fileno())
    temporary.replace(path)


def read_json(path: Path) -> dict[str, Any]:
    try:
        content = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"{path}: unreadable ({exc})") from exc
    if not isinstance(content, dict):
        raise ConfigurationError(f"{path}: not a JSON object")
    return content


class JsonLines:
    """An append-only log, one JSON object a line, each on disk before ``add`` returns. A
    torn last line (a crash mid-write) is skipped when read, and counted."""

    def __init__(self, path: Path):
        self.path = path

    def add(self, entry: dict[str, Any]) -> None:
        with open(self.path, "a+", encoding="utf-8") as handle:
            # after a torn last line the entry starts a line of its own (never glued to it)
            torn = handle.tell() > 0 and _last_byte(self.path) != b"\n"
            handle.write(("\n" if torn else "") + json.dumps(entry) + "\n")
            handle.flush()
            os.fsync(handle.fileno())

    def read(self) -> tuple[list[dict[str, Any]], int]:
        """The entries, and how many lines were unreadable."""
        if not self.path.exists():
            return [], 0
        entries, torn = [], 0
        for line in self.path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                torn += 1
                continue
            if isinstance(entry, dict):
                entries.append(entry)
            else:
                torn += 1
        return entries, torn


def _last_byte(path: Path) -> bytes:
    with open(path, "rb") as handle:
        handle.seek(-1, os.SEEK_END)
        return handle.read(1)


class Participant:
    """A pseudonymous participant's folder: their Latin-square row (from the enrolment
    ledger), their current calibration and their sessions."""

    def __init__(self, root: Path, participant: str):
        self.id = check_participant(participant)
        self.root = root
        self.folder = root / self.id
        self.file = self.folder / "participant.json"

    def enrol(self, rehearsal: bool = False) -> dict[str, Any]:
        """Their record, enrolling them on first sight: their row from the ledger, or, for
        a rehearsal, the row the next participant will take (a rehearsal uses none)."""
        if self.file.exists():
            record = read_json(self.file)
            if bool(record.get("rehearsal")) != rehearsal:
                said, flag = (
                    ("a rehearsal", "give --rehearsal")
                    if record.get("rehearsal")
                    else ("an enrolled participant", "leave out --rehearsal")
                )
                raise UsageError(
                    f"{self.id} is {said} under {self.root}: {flag}, or use another id"
                )
            return record
        ledger = Ledger(self.root)
        row = ledger.next_row() if rehearsal else ledger.enrol(self.id)
        self.folder.mkdir(parents=True, exist_ok=True)
        record = {"id": self.id, "row": row, "enrolled": now_utc(), "calibration": None}
        write_json(self.file, record | ({"rehearsal": True} if rehearsal else {}))
        return record

    @property
    def policy_folder(self) -> Path:
        """Where ``dammrl adapt --participant`` puts the policy refined for them; their
        sessions load it when it is there."""
        return self.folder / "policy"

    def refined_policy(self) -> Path | None:
        folder = self.policy_folder
        return folder if (folder / "checkpoint.pt").is_file() else None

    def next_candidate_folder(self) -> Path:
        """Where ``dammrl adapt --participant`` writes its next candidate policy."""
        candidates = self.folder / "policy-candidates"
        taken = [int(p.name) for p in candidates.glob("[0-9][0-9][0-9]") if p.is_dir()]
        return candidates / f"{max(taken, default=0) + 1:03d}"

    def deploy_policy(self, candidate: Path) -> Path:
        """Make ``candidate`` (a run directory) their policy; the one it replaces is kept
        beside the candidates as ``<n>-replaced``. Returns the policy folder."""
        staged = self.folder / "policy.new"
        shutil.rmtree(staged, ignore_errors=True)
        shutil.copytree(candidate, staged)
        if self.policy_folder.exists():
            retired = self.folder / "policy-candidates" / f"{candidate.name}-replaced"
            retired.parent.mkdir(parents=True, exist_ok=True)
            shutil.rmtree(retired, ignore_errors=True)
            self.policy_folder.rename(retired)
        staged.rename(self.policy_folder)
        return self.policy_folder

    def sessions(self) -> list[Path]:
        return sorted(p for p in self.folder.glob("ses-*") if (p / "session.json").exists())

    def keep_calibration(self, calibration: Path) -> Path:
        """Carry ``calibration`` to their later sessions: copied into their folder."""
        kept = self.folder / f"calibration{calibration.suffix or '.json'}"
        if calibration.resolve() != kept.resolve():
            shutil.copyfile(calibration, kept)
        record = read_json(self.file) | {"calibration": kept.name}
        write_json(self.file, record)
        return kept

    def posterior(self) -> tuple[float, float] | None:
        """The human-model posterior their earlier runs ended with (None: none yet)."""
        path = self.folder / "posterior.json"
        if not path.exists():
            return None
        p = read_json(path).get("probabilities")
        if not (isinstance(p, list) and len(p) == 2 and all(isinstance(v, float) for v in p)):
            raise ConfigurationError(f"{path}: no 'probabilities' of the two human models")
        return (p[0], p[1])

    def keep_posterior(self, probabilities: tuple[float, ...], session: str, trials: list[int]
                       ) -> None:  # fmt: skip
        """Carry the posterior a run ended with to the next run and session."""
        write_json(self.folder / "posterior.json", {
            "probabilities": [float(v) for v in probabilities], "session": session,
            "after_trials": trials, "utc": now_utc(),
        })  # fmt: skip

    def calibration(self) -> Path | None:
        """The calibration their last session kept, if any."""
        name = read_json(self.file).get("calibration")
        return None if not name else self.folder / str(name)


@dataclass
class Progress:
    """What a session folder says about its trials."""

    done: dict[int, dict[str, Any]]
    torn: int
    ended: bool


class SessionFolder:
    """One sitting's folder (see the module docstring)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.manifest = folder / "session.json"
        self.trials = JsonLines(folder / "trials.jsonl")
        self.events = JsonLines(folder / "events.jsonl")
        self.recordings = folder / "recordings"

    @classmethod
    def create(cls, participant: Participant, protocol: Protocol, protocol_file: Path,
               manifest: dict[str, Any]) -> SessionFolder:  # fmt: skip
        number = len(participant.sessions()) + 1
        folder = participant.folder / f"ses-{number:02d}"
        while folder.exists():  # a folder a crash left without its manifest: never reused
            number += 1
            folder = participant.folder / f"ses-{number:02d}"
        folder.mkdir(parents=True)
        session = cls(folder)
        session.recordings.mkdir()
        shutil.copyfile(protocol_file, folder / "protocol.yaml")
        write_json(session.manifest, manifest | {"session": folder.name, "started": now_utc()})
        return session

    def read_manifest(self) -> dict[str, Any]:
        return read_json(self.manifest)

    def progress(self) -> Progress:
        entries, torn = self.trials.read()
        done = {int(e["trial"]): e for e in entries
                if isinstance(e.get("trial"), int) and not e.get("repeat")}  # fmt: skip
        return Progress(done, torn, "ended" in self.read_manifest())

    def next_part(self) -> Path:
        """A recording file no run has used."""
        # the runs' own names (part-NN.mcap, a restarted recorder's part-NN-MMM.mcap); any
        # other file there (a file manager's "part-01 (copy).mcap") is no part of ours
        named = (re.fullmatch(r"part-(\d+)(-\d+)?", p.stem)
                 for p in self.recordings.glob("part-*.mcap"))  # fmt: skip
        parts = [int(match[1]) for match in named if match]
        return self.recordings / f"part-{max(parts, default=0) + 1:02d}.mcap"

    def end(self) -> None:
        write_json(self.manifest, self.read_manifest() | {"ended": now_utc()})


def differences(recorded: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """What changed between the set-up a session recorded and this one."""
    keys = sorted(set(recorded) | set(now))
    return [f"{k}: {recorded.get(k)!r} then, {now.get(k)!r} now" for k in keys
            if recorded.get(k) != now.get(k)]  # fmt: skip


def session_table(root: Path, participant: str | None = None) -> list[dict[str, Any]]:
    """One row per session under ``root`` (one participant's, if given)."""
    folders = [Participant(root, participant).folder] if participant else sorted(
        p for p in root.glob("*") if (p / "participant.json").exists()
    )  # fmt: skip
    rows = []
    for folder in folders:
        for path in sorted(folder.glob("ses-*/session.json")):
            session = SessionFolder(path.parent)
            manifest, progress = session.read_manifest(), session.progress()
            total = len(plan_trials(load_protocol(path.parent / "protocol.yaml"),
                                    int(manifest.get("row", 0))))  # fmt: skip
            successes = sum(bool((e.get("result") or {}).get("success"))
                            for e in progress.done.values())  # fmt: skip
            rows.append({"participant": folder.name, "session": path.parent.name,
                         "protocol": manifest["setup"]["protocol"],
                         "started": manifest.get("started", ""),
                         "trials": f"{len(progress.done)}/{total}",
                         "successes": successes,
                         "state": "ended" if progress.ended else "unfinished"})  # fmt: skip
    return rows
