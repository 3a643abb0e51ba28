"""What the recorder holds of each episode, and when it may say so (pure: no bus, no clock).

A session must not stop its stack before the recorder holds the episode it just logged:
the result, the arm's states up to the one the result was decided from (the result
names it: ``EpisodeResult.last_state_stamp_ns``, a stamp on the arm's own clock) and the
person's decisions it counts (``n_decisions``: as many of the episode's answered requests
in ``Intent``). The recorder hears the controller, the arm and the intent service on
separate links, so the result may come before the arm's last states or the last
decision; and on a loaded machine the bus may drop any of them.

:class:`EpisodeLedger` watches what is written. An episode is *due* an acknowledgement
once its result is written and the arm's stream has reached that state (complete), or
``wait_s`` after its result when it has not (incomplete, saying what is missing); a later
complete acknowledgement supersedes an incomplete one. When a file is finished its
metadata (``dammrl.episodes``) lists the episodes it holds a result of and the ones it
saw begin without their result: a tail it never received.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from schemas import EpisodeResult, Intent, RobotState, TaskGoal, type_of
from services.recorder.core import message_map
from services.recorder.gaps import publishers_of

LAST_STATE_WAIT_S = 5.0
"""How long after an episode's result the recorder waits for the arm's state the result
was decided from before it acknowledges the episode as incomplete [s]."""
METADATA = "dammrl.episodes"
"""The metadata record a finished file carries (see :meth:`EpisodeLedger.metadata`)."""


@dataclass(frozen=True)
class Ack:
    """An acknowledgement due: the fields of ``EpisodeRecorded`` but its header and file."""

    episode: int
    result_seq: int
    states: int
    complete: bool
    missing: str = ""


@dataclass
class _Episode:
    states: int = 0  # its robot states written
    last_t_s: float | None = None  # robot time of the newest of them
    begun: bool = False  # its goal or a state of it was written
    result_seq: int | None = None  # its result's sequence number, once written
    last_state_ns: int | None = None  # the state its result names
    answered: set[int] = field(default_factory=set)  # requests its Intents answered
    n_decisions: int = 0  # the decisions its result counts
    result_at_s: float = 0.0  # when the result was written (the caller's clock) [s]
    acked: bool | None = None  # None: not yet; False: as incomplete; True: complete
    lost: str = ""  # why some of it never reached the disk (a write error), if it did not


@dataclass
class EpisodeLedger:
    """The episodes in the files being written (keys under ``namespace``)."""

    namespace: str
    wait_s: float = LAST_STATE_WAIT_S
    episodes: dict[int, _Episode] = field(default_factory=dict)
    arm_stamp_ns: int = -1  # the newest robot state's header stamp written (the arm's clock)
    in_file: set[int] = field(default_factory=set)  # episodes with something in this file
    unflushed: set[int] = field(default_factory=set)  # episodes with something not on disk yet

    def written(self, key: str, payload: bytes, now_s: float) -> None:
        """A message written to the file (``now_s``: the caller's monotonic clock)."""
        kind = type_of(self.namespace, key)
        if kind not in (RobotState, TaskGoal, EpisodeResult, Intent):
            return
        fields = message_map(payload)
        if fields is None or not _from_publisher(self.namespace, key, fields):
            return
        episode = fields.get("episode")
        if type(episode) is not int or episode < (0 if kind is RobotState else 1):
            return
        if kind is RobotState:
            self._state(episode, fields)
        elif kind is TaskGoal:
            self._episode(episode).begun = True
        elif kind is Intent:
            if type(request := fields.get("request")) is int and request >= 0:
                self._episode(episode).answered.add(request)
        else:
            self._result(episode, fields, now_s)

    def due(self, now_s: float) -> list[Ack]:
        """The acknowledgements due now (each episode's once, and once more when an
        incomplete one becomes complete)."""
        acks = []
        for number, episode in sorted(self.episodes.items()):
            if episode.result_seq is None or episode.acked:
                continue
            complete = self._whole(episode)
            waited = now_s - episode.result_at_s >= self.wait_s
            if complete or (waited and episode.acked is None):
                episode.acked = complete
                acks.append(self._ack(number, episode, complete))
        return acks

    def metadata(self) -> dict[str, str]:
        """What a finished file holds of its episodes; then the next file starts afresh."""
        with_result = [n for n in sorted(self.in_file) if self.episodes[n].result_seq is not None]
        open_ = [n for n in sorted(self.in_file)
                 if self.episodes[n].begun and self.episodes[n].result_seq is None]  # fmt: skip
        partial = {str(n): self._missing(self.episodes[n]) for n in with_result
                   if not self._whole(self.episodes[n])}  # fmt: skip
        self.in_file = set()
        return {
            "results": json.dumps(with_result),
            "open_at_close": json.dumps(open_),
            "incomplete": json.dumps(partial),
        }

    def not_acknowledged(self, numbers: list[int]) -> None:
        """The acknowledgements of these episodes never went out (the sync before them
        failed): due again (they were dropped, and the session said "not confirmed")."""
        for number in numbers:
            self.episodes[number].acked = None

    def flushed(self) -> None:
        """Everything written so far is on disk (a chunk closed, a sync, a file finished)."""
        self.unflushed = set()

    def write_failed(self, why: str) -> None:
        """A write error left the file with what it held on disk: the episodes with
        messages not yet there lost them (never acknowledged complete after that)."""
        for number in self.unflushed:
            episode = self.episodes[number]
            episode.lost = episode.lost or why
        self.unflushed = set()

    def _episode(self, number: int) -> _Episode:
        self.in_file.add(number)
        self.unflushed.add(number)
        return self.episodes.setdefault(number, _Episode())

    def _state(self, number: int, fields: dict[str, Any]) -> None:
        self.arm_stamp_ns = max(self.arm_stamp_ns, fields["header"]["stamp_ns"])
        if number == 0:
            return  # the arm before the first episode
        episode = self._episode(number)
        episode.states += 1
        episode.begun = True
        t_s = fields.get("t_s")
        if isinstance(t_s, int | float) and not isinstance(t_s, bool):
            episode.last_t_s = float(t_s) if episode.last_t_s is None else max(
                episode.last_t_s, float(t_s))  # fmt: skip

    def _result(self, number: int, fields: dict[str, Any], now_s: float) -> None:
        episode = self._episode(number)
        if episode.result_seq is not None:
            return  # a repeat: the first one counts
        named = fields.get("last_state_stamp_ns")
        decisions = fields.get("n_decisions")
        episode.n_decisions = decisions if type(decisions) is int else 0
        episode.result_seq = fields["header"]["seq"]
        episode.last_state_ns = named if type(named) is int and named >= 0 else None
        episode.result_at_s = now_s

    def _whole(self, episode: _Episode) -> bool:
        whole = self._last_state_in(episode) and len(episode.answered) >= episode.n_decisions
        return whole and not episode.lost

    def _last_state_in(self, episode: _Episode) -> bool:
        return episode.last_state_ns is None or self.arm_stamp_ns >= episode.last_state_ns

    def _missing(self, episode: _Episode) -> str:
        missing = []
        if not self._last_state_in(episode):
            reached = "none" if episode.last_t_s is None else f"robot time {episode.last_t_s:.3f} s"
            missing.append(f"the robot state its result was decided from (the arm's states "
                           f"written reach {reached})")  # fmt: skip
        if episode.lost:
            missing.append(f"what a write error lost ({episode.lost})")
        if (written := len(episode.answered)) < episode.n_decisions:
            missing.append(f"{episode.n_decisions - written} of the {episode.n_decisions} "
                           f"decisions its result counts")  # fmt: skip
        return " and ".join(missing)

    def _ack(self, number: int, episode: _Episode, complete: bool) -> Ack:
        assert episode.result_seq is not None
        missing = "" if complete else self._missing(episode)
        return Ack(number, episode.result_seq, episode.states, complete, missing)


def _from_publisher(namespace: str, key: str, fields: dict[str, Any]) -> bool:
    """Only the key's own publisher (controller, arm) speaks for an episode."""
    expected = publishers_of(namespace, key)
    return expected is None or fields["header"].get("source") in expected
