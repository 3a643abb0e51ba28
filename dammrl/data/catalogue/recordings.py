"""A session's recordings, each read once and checked before use.

A stack run records ``part-NN.mcap`` and, after a restarted or rotating recorder, its
continuations ``part-NN-001.mcap`` ... Every file must carry a valid study tag naming the
participant and session of the folder it lies in, and (a continuation) the same run as
the others; a file that does not, or cannot be read, is passed over by name. A file cut
by a crash is used up to the cut and said so, with what was kept. What each run's files
hold of each episode (:class:`Reach`) is what the trial log is reconciled against.
"""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from dammrl.data.catalogue.tables import METRICS
from dammrl.stack.recording import Recording, RecordingError, read_recording
from dammrl_core.protocol import StudyTag
from dammrl_core.settings import error_line
from schemas import (
    ComfortRating,
    DecodeError,
    EmergencyStop,
    EpisodeResult,
    RobotState,
    SessionControl,
    TaskGoal,
    decode,
    type_of,
)
from services.common.security import OPERATOR, RETIRED_ROLES
from services.recorder.core import message_map

PART = re.compile(r"^(part-\d{2})(?:-\d{3})?\.mcap$")
"""A run's recording: ``part-NN.mcap`` or a continuation ``part-NN-NNN.mcap``."""
EPISODES_METADATA = "dammrl.episodes"
"""What a recorder writes when it finishes a file (``services.recorder.episodes``)."""

Rows = dict[str, list[tuple[Any, ...]]]


@dataclass
class Reach:
    """What a run's recordings hold of one episode."""

    episode: int
    begun: bool = False
    states: int = 0
    first_t_s: float | None = None  # robot time of its first and last state
    last_t_s: float | None = None
    last_state_ns: int = -1  # the newest of its states' header stamps (the arm's clock)
    states_missing: int = 0  # gaps in the arm's sequence numbers inside it
    result: EpisodeResult | None = None
    result_file: str = ""
    open_at_close: bool = False  # its recorder closed a file with it begun, no result


@dataclass
class FileCheck:
    """One file of a run: used or not, complete or cut, and what a person should know."""

    path: str  # relative to the root
    used: bool
    complete: bool = False
    messages: int = 0
    problem: str = ""
    cut: str = ""  # where and how the file stops, when it has no footer


@dataclass
class Run:
    """One stack run of a session: its files in the order they were written."""

    participant: str  # the folder's
    session: str
    part: str  # part-NN
    files: list[Path]
    study: StudyTag | None = None  # from its files' tags (None: none usable)
    checks: list[FileCheck] = field(default_factory=list)
    reaches: dict[int, Reach] = field(default_factory=dict)

    def reach(self, episode: int) -> Reach:
        return self.reaches.setdefault(episode, Reach(episode))

    def trial_of(self, episode: int) -> int | None:
        trials = self.study.trials if self.study is not None else []
        return trials[episode - 1] if 0 < episode <= len(trials) else None


def find_runs(root: Path) -> tuple[list[Run], list[str]]:
    """The stack runs under ``root`` (their files grouped, nothing read yet), and the files
    in a recordings folder that are no run's (said, never read)."""
    runs: dict[tuple[str, str, str], Run] = {}
    strays = []
    for path in sorted(root.glob("*/ses-*/recordings/*.mcap")):
        session, participant = path.parents[1].name, path.parents[2].name
        match = PART.match(path.name)
        if match is None:
            strays.append(f"{_relative(root, path)}: not read (no run's recording is named so: "
                          "part-NN.mcap, part-NN-NNN.mcap)")  # fmt: skip
            continue
        key = (participant, session, match.group(1))
        runs.setdefault(key, Run(participant, session, match.group(1), [])).files.append(path)
    for run in runs.values():
        run.files.sort(key=lambda p: (p.stem != run.part, p.name))  # the part, then in order
    return [runs[k] for k in sorted(runs)], strays


def read_run(root: Path, run: Run, rows: Rows) -> None:
    """Read each file of ``run`` once: check it, then take its rows into ``rows``."""
    reader = _RunReader(root, run, rows)
    for path in run.files:
        where = _relative(root, path)
        try:
            recording = read_recording(path)
        except RecordingError as exc:
            run.checks.append(FileCheck(where, used=False, problem=f"passed over: {exc}"))
            continue
        why = _tag_problem(recording, run)
        if why:
            run.checks.append(FileCheck(where, used=False, complete=recording.complete,
                                        problem=f"passed over: {why}"))  # fmt: skip
            continue
        cut = "" if recording.complete else recording.truncated_reason or "cut: no footer"
        check = FileCheck(where, used=True, complete=recording.complete,
                          messages=len(recording.messages), cut=cut)  # fmt: skip
        run.checks.append(check)
        reader.read(recording, where)
        check.problem = _damage(recording, run, check)


def _tag_problem(recording: Recording, run: Run) -> str:
    """Why this file's study tag keeps it out of ``run`` ("" when it belongs); the run's
    study is set from its first file that belongs."""
    text = recording.metadata.get("dammrl.session", {}).get("study", "")
    if not text:
        return "no session's recording (no study tag)"
    try:
        study = StudyTag.model_validate_json(text)
    except ValidationError as exc:
        return f"its study tag is not valid: {error_line(exc)}"
    if (study.participant, study.session) != (run.participant, run.session):
        return (f"its tag says {study.participant}/{study.session}, its folder "
                f"{run.participant}/{run.session}")  # fmt: skip
    if run.study is None:
        run.study = study
    elif study != run.study:
        return (
            f"its tag names another run (block {study.block}, trials {study.trials}) "
            f"than {run.part}'s (block {run.study.block}, trials {run.study.trials})"
        )
    return ""


def _damage(recording: Recording, run: Run, check: FileCheck) -> str:
    """What a person should know of a file used: cut (what was kept), records skipped."""
    said = []
    if check.cut:
        kept = [n for n, r in sorted(run.reaches.items()) if r.result_file == check.path]
        trials = [t for t in (run.trial_of(n) for n in kept) if t is not None]
        last = max((m.log_time for m in recording.messages), default=None)
        until = "" if last is None else f", its last message at {_utc(last)}"
        which = f" (trial{'s' if len(trials) > 1 else ''} {', '.join(map(str, trials))})"
        said.append(f"{check.cut}: kept {_count(len(kept), 'reach')}"
                    f"{which if trials else ''}{until}")  # fmt: skip
    for kind, count in sorted(recording.skipped.items()):
        said.append(f"{count} unreadable {kind} skipped")
    return "; ".join(said)


class _RunReader:
    """The rows of one run, from its files in order."""

    def __init__(self, root: Path, run: Run, rows: Rows) -> None:
        self.run, self.rows = run, rows
        self.who = (run.participant, run.session)
        self.starts: dict[int, int] = {}  # episode -> its TaskGoal's log time
        self.episode = 0  # the reach under way (for the therapist's acts)
        self.arm_seq: dict[str, int] = {}  # the arm's last sequence number, per source

    def read(self, recording: Recording, where: str) -> None:
        run, study = self.run, self.run.study
        assert study is not None
        if recording.messages:
            times = [m.log_time for m in recording.messages]
            protocol = (study.protocol, study.version, study.sha256)
            self.rows["runs"].append((*self.who, *protocol, where, min(times), max(times)))
        opened = recording.metadata.get(EPISODES_METADATA, {}).get("open_at_close", "[]")
        for episode in _int_list(opened):
            run.reach(episode).open_at_close = True
        for log_ns, message in self._messages(recording):
            self._take(message, log_ns, where)

    def _messages(self, recording: Recording) -> Iterator[tuple[int, Any]]:
        """The messages the catalogue reads, decoded; the arm's states by their few
        fields only (they are most of a recording)."""
        namespace = recording.namespace()
        wanted = (TaskGoal, EpisodeResult, ComfortRating, SessionControl, EmergencyStop)
        kinds = {cid: type_of(namespace, c.topic) for cid, c in recording.channels.items()}
        for record in recording.messages:
            kind = kinds.get(record.channel_id)
            if kind is RobotState:
                state = _state_fields(record.data)
                if state is not None:
                    yield record.log_time, state
            elif kind in wanted:
                assert kind is not None
                with contextlib.suppress(DecodeError):
                    yield record.log_time, decode(kind, record.data)

    def _take(self, message: Any, log_ns: int, where: str) -> None:
        if isinstance(message, _State):
            self._state(message)
        elif isinstance(message, TaskGoal):
            self.starts.setdefault(message.episode, log_ns)
            self.episode = message.episode
            self.run.reach(message.episode).begun = True
        elif isinstance(message, EpisodeResult):
            self._result(message, log_ns, where)
        elif isinstance(message, ComfortRating):
            self.rows["comfort"].append((*self.who, message.block, message.trial,
                                         message.rating, message.asked_s, where,
                                         log_ns))  # fmt: skip
        elif isinstance(message, SessionControl):
            self._act(message.episode, message.action, message.who, message.why,
                      _decision(message), where, log_ns)  # fmt: skip
        elif isinstance(message, EmergencyStop):
            who, why = _stop_author(message)
            action = "stop" if message.engaged else "release"
            self._act(self.episode, action, who, why, "", where, log_ns)

    def _state(self, state: _State) -> None:
        last = self.arm_seq.get(state.source)
        missing = state.seq - last - 1 if last is not None and state.seq > last else 0
        self.arm_seq[state.source] = state.seq
        if state.episode == 0:
            return
        reach = self.run.reach(state.episode)
        reach.begun = True
        if reach.states:
            reach.states_missing += missing  # inside the reach: between two of its states
        reach.states += 1
        reach.last_state_ns = max(reach.last_state_ns, state.stamp_ns)
        reach.first_t_s = state.t_s if reach.first_t_s is None else min(reach.first_t_s,
                                                                         state.t_s)  # fmt: skip
        reach.last_t_s = state.t_s if reach.last_t_s is None else max(reach.last_t_s, state.t_s)

    def _result(self, result: EpisodeResult, log_ns: int, where: str) -> None:
        reach = self.run.reach(result.episode)
        trial = self.run.trial_of(result.episode)
        if reach.result is not None or trial is None:
            return  # a repeat of a result taken, or an episode beyond the run's trials
        reach.result, reach.result_file = result, where
        self.rows["trials"].append(self._trial_row(trial, result, log_ns, where))

    def _act(self, episode: int, action: str, who: str, why: str, detail: str, where: str,
             log_ns: int) -> None:  # fmt: skip
        trial = self.run.trial_of(episode)
        self.rows["actions"].append((*self.who, trial, action, who, why, detail, where, log_ns))

    def _trial_row(self, trial: int, result: EpisodeResult, log_ns: int, where: str
                   ) -> tuple[Any, ...]:  # fmt: skip
        study = self.run.study
        assert study is not None
        condition = study.condition
        metrics = result.model_dump()
        return (
            *self.who,
            study.block,
            trial,
            0,
            False,
            study.practice,
            None if condition is None else condition.policy,
            result.trigger,
            result.model[0],
            result.model[1],
            result.seed,
            *(metrics[name] for name in METRICS),
            where,
            result.episode,
            self.starts.get(result.episode, log_ns),
            log_ns,
        )


@dataclass(frozen=True)
class _State:
    """The few fields of a robot state the catalogue needs."""

    source: str
    seq: int
    stamp_ns: int
    episode: int
    t_s: float


def _state_fields(payload: bytes) -> _State | None:
    """A robot state's fields, read without validating the rest (None when malformed)."""
    fields = message_map(payload)
    if fields is None:
        return None
    header, episode, t_s = fields["header"], fields.get("episode"), fields.get("t_s")
    source, stamp_ns = header.get("source"), header["stamp_ns"]
    if type(episode) is not int or episode < 0 or not isinstance(source, str) or stamp_ns < 0:
        return None
    if not isinstance(t_s, int | float) or isinstance(t_s, bool) or not t_s >= 0:
        return None
    return _State(source, header["seq"], stamp_ns, episode, float(t_s))


def _decision(control: SessionControl) -> str:
    if control.action != "decide":
        return ""
    way = "forward" if control.u_h == 1 else "back"
    return f"{way}, radius {'big' if control.human_model == 1 else 'small'}"


def _stop_author(stop: EmergencyStop) -> tuple[str, str]:
    """Who stopped and why: the session console writes ``"<operator>: <why>"`` (from the
    operator's certificate; earlier recordings from the one 'tool' certificate); any other
    sender is its source."""
    if stop.header.source in (OPERATOR, *RETIRED_ROLES) and ": " in stop.reason:
        who, why = stop.reason.split(": ", 1)
        return who, why
    return stop.header.source, stop.reason


def _int_list(text: str) -> list[int]:
    try:
        values = json.loads(text)
    except ValueError:
        return []
    return [v for v in values if type(v) is int] if isinstance(values, list) else []


def _relative(root: Path, path: Path) -> str:
    return path.relative_to(root).as_posix()


def _utc(log_ns: int) -> str:
    return datetime.fromtimestamp(log_ns / 1e9, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "es" if noun.endswith("ch") else "s")
