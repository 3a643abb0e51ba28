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
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from types import UnionType
from typing import Literal, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dammrl_core.coadaptation import Targets
from dammrl_core.errors import ConfigurationError
from dammrl_core.models import HUMAN_MODELS, ROBOT_MODELS

FORMAT: Literal[1] = 1
"""The protocol file format this version of dammrl reads."""
MAX_TRIALS = 500
"""Trials in a block at most: a stack run's trial numbers go into its recording's study
tag, which fits the recorder's 4 KiB of metadata."""
MAX_SEED = 2**31 - 1
"""The largest task seed (the seed streams take 31 bits)."""


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
        if self.model is not None and (
            self.model[0] not in HUMAN_MODELS or self.model[1] not in ROBOT_MODELS
        ):
            raise ValueError(
                f"model {list(self.model)}: i (the human model) is one of "
                f"{_listed(HUMAN_MODELS)}, j (the robot model) one of {_listed(ROBOT_MODELS)}"
            )
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
    trials: list[int] = Field(min_length=1, max_length=MAX_TRIALS)

    @model_validator(mode="after")
    def _trial_numbers(self) -> StudyTag:
        if any(t < 1 for t in self.trials):
            raise ValueError("trial numbers count from 1")
        return self


class Block(_Strict):
    """Trials under one condition, one reach each, seeds ``seed``, ``seed + 1``, ..."""

    name: str = Field(min_length=1, max_length=64, pattern=NAME)
    trials: int = Field(ge=1, le=MAX_TRIALS)
    seed: int = Field(ge=0, le=MAX_SEED)
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


class ProtocolError(ConfigurationError):
    """A protocol that cannot run: every problem found, one plain line each (``problems``),
    each naming the field and what it allows."""

    def __init__(self, source: Path | str, problems: list[str]) -> None:
        self.problems = tuple(problems)
        count = "1 problem" if len(problems) == 1 else f"{len(problems)} problems"
        super().__init__(f"protocol {source}: {count}: " + "; ".join(problems))


def load_protocol(path: Path) -> Protocol:
    """Read and validate a protocol file (YAML or JSON); a ProtocolError listing every
    problem of its structure (values out of range, unknown keys, bad names)."""
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ProtocolError(path, [f"cannot read it: {_short(exc)}"]) from exc
    if not isinstance(raw, dict):
        raise ProtocolError(path, ["not a mapping of settings (format, name, version, blocks)"])
    try:
        return Protocol.model_validate(raw)
    except ValidationError as exc:
        raise ProtocolError(path, plain_problems(exc, raw)) from exc


def check_protocol(protocol: Protocol, intent_sources: Collection[str]) -> list[str]:
    """What a valid protocol asks that cannot run here (one plain line each; [] when it
    can): an intent source not installed, seeds past the largest."""
    problems = []
    for number, block in enumerate(protocol.blocks, start=1):
        where = f"block {number} ({block.name})"
        intent = block.condition.intent
        if intent is not None and intent not in intent_sources:
            problems.append(f"{where}: condition.intent {intent!r} is no installed intent "
                            f"source; allowed: {', '.join(sorted(intent_sources))}")  # fmt: skip
        last = block.seed + block.trials - 1
        if last > MAX_SEED:
            problems.append(f"{where}: seed {block.seed} with {block.trials} trials runs to "
                            f"seed {last}; allowed: seeds up to {MAX_SEED}")  # fmt: skip
    return problems


def plain_problems(exc: ValidationError, raw: dict[str, object]) -> list[str]:
    """A protocol's validation errors as plain lines: where (the block by number and
    name, the field), what was given and what the field allows."""
    lines = []
    errors = exc.errors(include_url=False)
    inner = {tuple(e["loc"])[:n] for e in errors for n in range(len(e["loc"]))}
    for error in errors:
        loc = tuple(error["loc"])
        if error["type"] == "too_short" and loc in inner:
            continue  # pydantic counts the items left after its own errors: no news
        where = _where(loc, raw)
        kind = error["type"]
        if kind == "extra_forbidden":
            allowed = ", ".join(_model_at(loc[:-1]).model_fields)
            what = f"unknown key; allowed keys: {allowed}"
        elif kind == "missing":
            what = f"missing; it takes {_allowed(loc)}"
        elif kind in ("value_error", "assertion_error") or not loc:
            what = str(error["msg"]).removeprefix("Value error, ")
        else:
            what = f"{_shown(error.get('input'))} is not allowed; it takes {_allowed(loc)}"
        lines.append(f"{where}: {what}" if where else what)
    return lines


def _where(loc: tuple[int | str, ...], raw: dict[str, object]) -> str:
    """``block 2 (fixed): condition.trigger`` for ('blocks', 1, 'condition', 'trigger')."""
    if len(loc) >= 2 and loc[0] == "blocks" and isinstance(loc[1], int):
        blocks = raw.get("blocks")
        entry = blocks[loc[1]] if isinstance(blocks, list) and loc[1] < len(blocks) else None
        name = entry.get("name") if isinstance(entry, dict) else None
        block = f"block {loc[1] + 1}" + (f" ({name})" if isinstance(name, str) else "")
        rest = _dotted(loc[2:])
        return f"{block}: {rest}" if rest else block
    return _dotted(loc)


def _dotted(loc: tuple[int | str, ...]) -> str:
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else ("." if text else "") + part
    return text


def _field(loc: tuple[int | str, ...]) -> tuple[object, list[object]]:
    """The annotation and the constraints of the protocol's field at ``loc``."""
    annotation: object = Protocol
    metadata: list[object] = []
    for part in loc:
        annotation = _optional(annotation)
        if isinstance(part, str) and isinstance(annotation, type) and issubclass(
            annotation, BaseModel
        ):  # fmt: skip
            info = annotation.model_fields.get(part)
            if info is None:
                return None, []
            annotation, metadata = info.annotation, list(info.metadata)
        elif isinstance(part, int) and get_origin(annotation) in (tuple, list):
            args = get_args(annotation)
            annotation = args[0] if args[-1] is Ellipsis or len(args) == 1 else args[part]
            metadata = []
    return _optional(annotation), metadata


def _model_at(loc: tuple[int | str, ...]) -> type[BaseModel]:
    annotation, _ = _field(loc)
    return (
        annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel)
        else Protocol
    )


def _optional(annotation: object) -> object:
    """``X`` for ``X | None``."""
    if get_origin(annotation) in (Union, UnionType):
        rest = [a for a in get_args(annotation) if a is not type(None)]
        return rest[0] if len(rest) == 1 else annotation
    return annotation


def _allowed(loc: tuple[int | str, ...]) -> str:
    """What the field at ``loc`` takes, in words."""
    annotation, metadata = _field(loc)
    bounds = {k: getattr(m, k) for m in metadata for k in ("ge", "gt", "le", "lt", "max_length")
              if getattr(m, k, None) is not None}  # fmt: skip
    origin, args = get_origin(annotation), get_args(annotation)
    if origin is Literal:
        return "one of " + ", ".join(str(a) for a in args)
    if annotation is bool:
        return "true or false"
    if annotation in (int, float):
        kind = "a whole number" if annotation is int else "a number"
        low = bounds.get("ge", bounds.get("gt"))
        high = bounds.get("le", bounds.get("lt"))
        above = "" if "gt" not in bounds else " (above it)"
        below = "" if "lt" not in bounds else " (below it)"
        if low is not None and high is not None:
            return f"{kind} from {low}{above} to {high}{below}"
        return kind if low is None else f"{kind} of at least {low}{above}"
    if annotation is str:
        length = bounds.get("max_length")
        pattern = next((getattr(m, "pattern", None) for m in metadata
                        if getattr(m, "pattern", None)), None)  # fmt: skip
        what = "letters, digits, '_', '.' and '-'" if pattern == NAME else "text"
        return what + ("" if length is None else f" of at most {length} characters")
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "a mapping of " + ", ".join(annotation.model_fields)
    if origin in (tuple, list):
        if args and args[-1] is not Ellipsis and len(args) > 1:
            return f"a list of {len(args)} values"
        return "a list"
    return "another value"


def _shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _listed(values: tuple[int, ...]) -> str:
    return f"{values[0]}..{values[-1]}" if len(values) > 2 else ", ".join(map(str, values))


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
