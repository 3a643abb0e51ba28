"""Each session's trial log (``trials.jsonl``) reconciled with its recordings.

A trial counts as done once its line is in the log; the catalogue is built from the
recordings. The two must agree, and where they do not, a person is told which trial and
why: every line with a reach is found in the recordings whole (``recorded``), with its
result but not all of the arm's states (``partial``), or not at all (``missing``, with
what the recordings hold instead); a line without a reach is ``skipped``; a reach
recorded with no line is ``unlogged``. A line names its run's recording and the episode
in it; the run's file may have continued in ``part-NN-001.mcap`` and on.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dammrl.data.catalogue.recordings import PART, Reach, Run
from dammrl.people.session import JsonLines

STATE_SPAN_SLACK_S = 0.05
"""A result that names no last state (recorded before results did) is partial when its
states span less than its reach's time by more than this [s] (two control periods)."""


@dataclass(frozen=True)
class Line:
    """One line's reconciliation: a row of ``completeness``."""

    participant: str
    session: str
    trial: int | None
    block: str | None
    line: int | None  # its line number in trials.jsonl (None: unlogged)
    recording: str | None
    episode: int | None
    status: str
    reason: str

    def row(self) -> tuple[Any, ...]:
        return (self.participant, self.session, self.trial, self.block, self.line,
                self.recording, self.episode, self.status, self.reason)  # fmt: skip

    def said(self) -> str:
        """The line a person reads on stderr."""
        what = {"missing": "missing from the recordings", "partial": "recorded in part",
                "unlogged": "recorded but not in trials.jsonl"}[self.status]  # fmt: skip
        return f"{self.participant}/{self.session} trial {self.trial}: {what}: {self.reason}"


def reconcile(folder: Path, participant: str, session: str, runs: Iterable[Run]) -> list[Line]:
    """Every line of the session's log and every recorded reach without one, reconciled."""
    entries, torn = JsonLines(folder / "trials.jsonl").read()
    by_part = {run.part: run for run in runs}
    unconfirmed = _unconfirmed(folder)
    lines, seen = [], set()
    for number, entry in enumerate(entries, start=1):
        line = _reconcile(entry, number, by_part, unconfirmed, (participant, session))
        lines.append(line)
        part = _part_of(line.recording)
        if part is not None and line.episode is not None:
            seen.add((part, line.episode))
    if torn:
        lines.append(
            Line(
                participant,
                session,
                None,
                None,
                None,
                None,
                None,
                "missing",
                f"{torn} line(s) of trials.jsonl unreadable (torn by a crash)",
            )
        )
    if entries or torn:
        lines += _unlogged(participant, session, by_part, seen)
    return lines


def _part_of(recording: str | None) -> str | None:
    """``part-NN`` of a recording's name (a continuation's too); None if none."""
    match = PART.match((recording or "").rsplit("/", 1)[-1])
    return None if match is None else match.group(1)


def _reconcile(entry: dict[str, Any], number: int, by_part: dict[str, Run],
               unconfirmed: dict[tuple[str, int], str], who: tuple[str, str]) -> Line:  # fmt: skip
    trial, block = entry.get("trial"), entry.get("block")
    recording, episode = entry.get("recording"), entry.get("episode")
    recording = recording if isinstance(recording, str) else None
    episode = episode if type(episode) is int else None
    line = Line(*who, trial if type(trial) is int else None,
                block if isinstance(block, str) else None, number, recording, episode,
                "recorded", "")  # fmt: skip
    if entry.get("result") is None:
        why = entry.get("skipped")
        reason = f"skipped by {why}" if isinstance(why, str) and why else "no reach run"
        return _with(line, "skipped", reason)
    part = _part_of(recording)
    if part is None or episode is None:
        return _with(line, "missing", "its log line names no recording and episode")
    run = by_part.get(part)
    reason = _why_missing(run, part, episode, entry.get("result"), line.trial)
    if reason:
        note = unconfirmed.get((part, episode))
        return _with(line, "missing", reason + (f"; {note}" if note else ""))
    assert run is not None
    reach = run.reaches[episode]
    assert reach.result is not None
    part = _partly(reach)
    return _with(line, "partial", part) if part else line


def _with(line: Line, status: str, reason: str) -> Line:
    return Line(line.participant, line.session, line.trial, line.block, line.line,
                line.recording, line.episode, status, reason)  # fmt: skip


def _why_missing(run: Run | None, part: str, episode: int, logged: Any,
                 trial: int | None) -> str:  # fmt: skip
    """Why the recordings hold no result of the line's reach ("" when they hold it)."""
    if run is None:
        return f"its recording {part}.mcap does not exist"
    unused = [c for c in run.checks if not c.used]
    if run.study is None:
        problems = "; ".join(f"{c.path.rsplit('/', 1)[-1]} {c.problem}" for c in unused)
        return f"no file of its recording {part}.mcap was usable ({problems})"
    reach = run.reaches.get(episode)
    if reach is not None and reach.result is not None:
        recorded = run.trial_of(episode)
        if recorded != trial:
            return f"{part} holds episode {episode} as trial {recorded}, the log as {trial}"
        return ""
    return _what_is_there(run, part, episode, reach, logged)


def _what_is_there(run: Run, part: str, episode: int, reach: Reach | None, logged: Any) -> str:
    cut = next((c for c in run.checks if c.used and c.cut), None)
    where = f"{part}.mcap" if cut is None else cut.path.rsplit("/", 1)[-1]
    lost = "the recorder never received the reach's tail" if cut is None else (
        f"the file is {cut.cut}")  # fmt: skip
    if reach is None or not reach.begun:
        return f"{where} holds nothing of its reach (episode {episode}): {lost}"
    logged_s = logged.get("t_total_s") if isinstance(logged, dict) else None
    of = f" of {logged_s:.2f} s" if isinstance(logged_s, int | float) else ""
    if reach.states and reach.first_t_s is not None and reach.last_t_s is not None:
        span = f"its states up to {reach.last_t_s - reach.first_t_s:.2f} s{of}"
    else:
        span = "its start but no state"
    closed = " (the recorder closed the file with the reach open)" if reach.open_at_close else ""
    return f"{where} holds {span} and no result: {lost}{closed}"


def _partly(reach: Reach) -> str:
    """What of the arm's states a reach with its result lacks ("" when whole)."""
    result = reach.result
    assert result is not None
    said = []
    named = result.last_state_stamp_ns
    if reach.states == 0:
        said.append("no state of the arm in it was recorded")
    elif named is not None and reach.last_state_ns < named:
        short = (named - reach.last_state_ns) * 1e-9
        said.append(f"the arm's states stop {short:.2f} s before the one its result was "
                    "decided from")  # fmt: skip
    elif named is None and reach.first_t_s is not None and reach.last_t_s is not None:
        span = reach.last_t_s - reach.first_t_s
        if span < result.t_total_s - STATE_SPAN_SLACK_S:
            said.append(f"the arm's states cover {span:.2f} s of its {result.t_total_s:.2f} s")
    if reach.states_missing:
        said.append(f"{reach.states_missing} of its {reach.states + reach.states_missing} "
                    "arm states missing inside it")  # fmt: skip
    return "; ".join(said)


def _unlogged(participant: str, session: str, by_part: dict[str, Run],
              seen: set[tuple[str, int]]) -> list[Line]:  # fmt: skip
    lines = []
    for part, run in sorted(by_part.items()):
        for episode, reach in sorted(run.reaches.items()):
            if reach.result is None or (part, episode) in seen:
                continue
            study = run.study
            lines.append(Line(participant, session, run.trial_of(episode),
                              None if study is None else study.block, None,
                              f"recordings/{reach.result_file.rsplit('/', 1)[-1]}", episode,
                              "unlogged", "the session stopped before logging it (the trial "
                              "ran again)"))  # fmt: skip
    return lines


def _unconfirmed(folder: Path) -> dict[tuple[str, int], str]:
    """(part, episode) -> that the session runner heard no acknowledgement of it from the
    recorder (``events.jsonl``, its ``recorded`` events)."""
    events, _ = JsonLines(folder / "events.jsonl").read()
    said = {}
    for event in events:
        part = _part_of(event.get("recording") if event.get("what") == "recorded" else None)
        episodes = event.get("unconfirmed_episodes")
        if part is None or not isinstance(episodes, list):
            continue
        for episode in episodes:
            if type(episode) is int:
                said[(part, episode)] = (f"the recorder did not confirm it on disk (the "
                                         f"session waited {event.get('waited_s')} s)")  # fmt: skip
    return said
