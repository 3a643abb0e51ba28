"""A study protocol as a file: blocks of trials with their conditions, practice, rests,
instructions and counterbalancing across participants.

A protocol is what a lab writes once and runs with every participant, as task files of
blocks and trials are in published point-to-point protocols for rehabilitation robots.
It is validated here (unknown keys are refused: a typo must not silently change a study),
versioned, and identified by the SHA-256 of its canonical form, which every session and
recording carries. Pure data: no bus, no files but the one read.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from dammrl_core.coadaptation import Targets
from dammrl_core.errors import ConfigurationError

FORMAT: Literal[1] = 1
"""The protocol file format this version of dammrl reads."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Condition(_Strict):
    """What a block varies: how progression is triggered, who chooses M_ij, who decides."""

    trigger: Literal["event", "fixed"] = "event"
    policy: Literal["learned", "fixed", "adaptive"] = "learned"
    """learned: the shipped DAMMRL policy; fixed: ``model`` throughout; adaptive: the
    shipped policy with the posterior over M_ij, re-selecting when ``targets`` are missed."""
    targets: Targets | None = None
    """What an adaptive block asks of its last reaches (default: Targets())."""
    model: tuple[int, int] | None = None
    """M_ij for a fixed policy (human model i, robot model j)."""
    intent: str | None = None
    """Who decides: simulated, pad, lsl or an installed source; None: the session's set-up
    (the device given to ``dammrl session run``)."""

    @model_validator(mode="after")
    def _model_with_fixed(self) -> Condition:
        if (self.policy == "fixed") != (self.model is not None):
            raise ValueError("a fixed policy needs its model [i, j], a learned one none")
        if self.targets is not None and self.policy != "adaptive":
            raise ValueError("targets are for an adaptive policy")
        if self.model is not None and not all(1 <= m <= 9 for m in self.model):
            raise ValueError(f"model {list(self.model)}: i and j count from 1")
        return self


PARTICIPANT_ID = r"^[A-Za-z]{1,4}[0-9]{1,6}$"
"""A pseudonym such as P012: letters then digits, nothing a name could hide in."""
SESSION_ID = r"^ses-[0-9]{2,4}$"
"""A session's folder: ses-01, ses-02, ..."""
NAME = r"^[A-Za-z0-9_.-]+$"
"""A protocol's or a block's name: it names files and shows in reports."""


class StudyTag(_Strict):
    """What a session's stack run served, written into its recording's metadata
    (``dammrl.session`` -> ``study``) and read back by the catalogue: the recordings alone
    say whose trials they hold. A tag that does not validate is no session's."""

    participant: str = Field(pattern=PARTICIPANT_ID)
    session: str = Field(pattern=SESSION_ID)
    protocol: str = Field(max_length=64, pattern=NAME)
    version: str = Field(max_length=32)
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    block: str = Field(max_length=64, pattern=NAME)
    practice: bool = False
    condition: Condition | None = None  # None: recorded before the tag carried it
    trials: list[int] = Field(min_length=1, max_length=500)  # the tag fits the recorder's 4 KiB

    @model_validator(mode="after")
    def _trial_numbers(self) -> StudyTag:
        if any(t < 1 for t in self.trials):
            raise ValueError("trial numbers count from 1")
        return self


class Block(_Strict):
    """Trials under one condition, one reach each, seeds ``seed``, ``seed + 1``, ..."""

    name: str = Field(min_length=1, max_length=64, pattern=NAME)
    trials: int = Field(ge=1, le=1000)
    seed: int = Field(ge=0, lt=2**31)
    """The first trial's task seed (start and goal); held out from training by convention
    (the study's seeds start at 7,000,000)."""
    condition: Condition = Condition()
    practice: bool = False
    """Practice blocks come first, in file order, and are not counterbalanced."""
    rest_s: float = Field(0.0, ge=0.0, le=3600.0)
    """A rest after the block [s] (the therapist may end it early)."""
    instructions: str = Field("", max_length=2000)
    """Shown to the participant before the block."""


class Protocol(_Strict):
    """A study protocol (see the module docstring)."""

    format: Literal[1] = FORMAT
    name: str = Field(min_length=1, max_length=64, pattern=NAME)
    version: str = Field(min_length=1, max_length=32)
    description: str = Field("", max_length=4000)
    counterbalance: Literal["latin-square", "none"] = "latin-square"
    """latin-square: the test blocks' order follows a balanced Latin square (Williams),
    one row per participant in the order they were enrolled."""
    blocks: tuple[Block, ...] = Field(min_length=1, max_length=100)
    comfort: Literal["after-block", "none"] = "after-block"
    """Ask the participant's comfort (1-5) on the display after each block."""

    @model_validator(mode="after")
    def _names_unique(self) -> Protocol:
        names = [b.name for b in self.blocks]
        if len(set(names)) != len(names):
            raise ValueError(f"block names repeat: {names}")
        if not any(not b.practice for b in self.blocks):
            raise ValueError("a protocol needs a block that is not practice")
        return self

    @property
    def sha256(self) -> str:
        """The hash of the canonical form (whitespace, key order and comments of the file
        do not change it; any value does)."""
        canonical = json.dumps(self.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()

    @property
    def test_blocks(self) -> tuple[Block, ...]:
        return tuple(b for b in self.blocks if not b.practice)


def load_protocol(path: Path) -> Protocol:
    """Read and validate a protocol file (YAML or JSON); a ConfigurationError naming the
    file and what is wrong."""
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigurationError(f"protocol {path}: cannot read it: {_short(exc)}") from exc
    if not isinstance(raw, dict):
        raise ConfigurationError(f"protocol {path}: not a mapping of settings")
    try:
        return Protocol.model_validate(raw)
    except ValueError as exc:
        raise ConfigurationError(f"protocol {path}: {_short(exc)}") from exc


def _short(exc: Exception) -> str:
    return " ".join(str(exc).split())[:400]


def balanced_latin_square(n: int) -> list[list[int]]:
    """Orders of ``n`` conditions in which each comes in each position equally often and,
    for even ``n``, follows each other once (Williams 1949). Odd ``n`` gives 2n rows: the
    square and its mirror."""
    first = [0] + [((k + 1) // 2 if k % 2 else n - k // 2) % n for k in range(1, n)]
    rows = [[(c + r) % n for c in first] for r in range(n)]
    return rows if n % 2 == 0 else rows + [row[::-1] for row in rows]


@dataclass(frozen=True)
class Trial:
    """One reach of a session: its place in the protocol and what it runs."""

    number: int
    """Its position in the session, from 1."""
    block: str
    block_position: int
    """The block's position in this participant's order, from 1."""
    index: int
    """Its position in its block, from 1."""
    seed: int
    condition: Condition
    practice: bool


def block_order(protocol: Protocol, row: int) -> list[Block]:
    """The blocks in the order participant ``row`` (their enrolment index, from 0) runs
    them: practice first, then the test blocks in Latin-square row ``row``."""
    practice = [b for b in protocol.blocks if b.practice]
    tests = list(protocol.test_blocks)
    if protocol.counterbalance == "none":
        return practice + tests
    square = balanced_latin_square(len(tests))
    return practice + [tests[i] for i in square[row % len(square)]]


def plan_trials(protocol: Protocol, row: int) -> list[Trial]:
    """Every trial of a session for participant ``row``, in the order they run."""
    trials: list[Trial] = []
    for position, block in enumerate(block_order(protocol, row), start=1):
        for index in range(1, block.trials + 1):
            seed = block.seed + index - 1
            trial = Trial(len(trials) + 1, block.name, position, index, seed, block.condition,
                          block.practice)  # fmt: skip
            trials.append(trial)
    return trials
