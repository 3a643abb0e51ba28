"""Where the human agent's decisions come from, behind one interface, and the registry of
its plug-ins.

An ``IntentSource`` answers the open decision request with a binary command u_h, an
admission radius i, a confidence and the time the decision took: a simulated human
(virtual mode), a pressure pad (semi-virtual), a wearable sensor's classifier, a lab's
own device. The intent service runs any of them (the request/answer bookkeeping is
written once, there); an ``IntentSourcePlugin`` is what a package registers under the
entry-point group ``dammrl.intent_sources``: its name, its own settings class (an
environment prefix of its own) and how to make the source. Choosing one is a setting
(``DAMMRL_INTENT_SOURCE``), never an edit of dammrl.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, cast, runtime_checkable

import numpy as np

from dammrl_core import plugins
from dammrl_core.human import HumanModel
from dammrl_core.models import ModelSet
from dammrl_core.settings import Settings

ENTRY_POINTS = "dammrl.intent_sources"


@dataclass(frozen=True)
class Ask:
    """An open decision request, as a source sees it."""

    episode: int
    request: int
    seed: int  # the episode's task seed
    t_s: float  # robot time of the request [s]
    ee_pos_m: np.ndarray  # (3,) where the hand is
    goal_m: np.ndarray  # (3,) where the goal is
    primary_axis: int  # 0 = x, 1 = y, 2 = z: the axis u_h drives
    human_model: int  # the radius i to decide with (the policy's, or the request's own)


@dataclass(frozen=True)
class Decided:
    """A decision for the open request."""

    u_h: int  # -1 or +1
    human_model: int  # the radius i decided with
    confidence: float  # [0, 1]: the source's probability of u_h
    decision_s: float  # from the request to the decision [s]
    correct: bool | None = None  # toward the goal (known only in simulation)


@dataclass(frozen=True)
class Reading:
    """One raw sample of the source's sensor, published as it comes (``sensor/sample``)."""

    device_seq: int
    raw: int
    level: float  # normalised (the source's calibration)
    active: bool  # the person is acting (a press held, a contraction)


@dataclass(frozen=True)
class Chunk:
    """Raw samples of a streaming sensor as they came (``sensor/chunk``)."""

    stream: str  # the stream's name
    rate_hz: float  # its nominal rate
    samples: np.ndarray  # (n, channels), the stream's units
    times_s: np.ndarray  # (n,) on this machine's monotonic clock [s]
    missing: int = 0  # samples missing just before these (a gap in the stream)
    clock_corrected_s: float = 0.0  # added to the stream's stamps since they jumped [s]


@dataclass(frozen=True)
class Evidence:
    """A decision of a classifying source, acted on or not (``intent/evidence``)."""

    request: int  # the open request it answered, -1 when none was open
    u_h: int
    human_model: int
    confidence: float
    onset_s: float  # this machine's monotonic clock [s]
    decided_s: float  # the sample that completed the decision, same clock [s]
    duration_s: float
    windows: int
    features: tuple[float, ...]
    acted: bool
    reason: str  # why it was not acted on


def belongs_to_request(onset_s: float, opened_s: float | None, tolerance_s: float) -> str:
    """Why a decision whose action began at ``onset_s`` does not answer the request open
    since ``opened_s`` (None: none open), or "" when it does. A press or a contraction
    that began before the request opened was meant for another moment (a closed request,
    or none): it answers nothing, even if it ends while one is open. ``tolerance_s``:
    the onset estimate's error [s]; clocks: this machine's monotonic one."""
    if opened_s is None:
        return "no request open"
    early = opened_s - onset_s
    if early > tolerance_s:
        return f"began {early:.2f} s before the request opened"
    return ""


@runtime_checkable
class Rebaselining(Protocol):
    """A source whose decoder tracks a rest level, measured afresh when asked."""

    def rebaseline(self) -> str:
        """Start measuring (the participant rests); what is done, in a few words."""
        ...


@runtime_checkable
class StreamingSource(Protocol):
    """What a source that classifies a raw stream adds: the stream itself (kept so a
    session can be decoded again offline) and the evidence of every decision."""

    def chunks(self) -> list[Chunk]:
        """The raw samples since the last call."""
        ...

    def evidence(self) -> list[Evidence]:
        """The decisions made since the last call, acted on or not."""
        ...


@dataclass(frozen=True)
class SourceContext:
    """What the stack gives every source: the model set and the simulated human's model."""

    models: ModelSet
    human: HumanModel
    lockstep: bool = False  # the robot clock waits for the answer (simulation only)


class IntentSource(Protocol):
    person: bool
    """True when a person decides (a sensor): the policy then estimates who they are."""
    waits_for_model_choice: bool
    """True when the source decides with the policy's radius (the simulated human); a
    person picks their own (the pad's quick or held press)."""

    def open(self) -> None:
        """Start (open a device); a setting that cannot work raises DammrlError."""
        ...

    def close(self) -> None: ...

    def new_episode(self, episode: int, seed: int) -> None:
        """A new episode (seeds a simulated human; a person just goes on)."""
        ...

    def ask(self, ask: Ask, now_s: float) -> None:
        """A request is open from wall time ``now_s`` (a new ask replaces an older one)."""
        ...

    def cancel(self) -> None:
        """The open request closed unanswered (a new episode began)."""
        ...

    def poll(self, now_s: float) -> Decided | None:
        """Read and decode what came (waiting a few milliseconds at most); the decision for
        the open request once one is made (a decision with none open is not one)."""
        ...

    def readings(self) -> list[Reading]:
        """The raw samples since the last call (none for a simulated human)."""
        ...

    def problem(self) -> str | None:
        """What keeps it from deciding now (a device gone, a sensor stuck), or None."""
        ...

    def detail(self) -> str:
        """A line for Health when all is well (counts, rates)."""
        ...


class IntentSourcePlugin(Protocol):
    """An intent source as a package provides it (entry-point group ``dammrl.intent_sources``)."""

    name: str
    settings: type[Settings]
    """Its own settings (device, calibration file, thresholds), with a prefix of its own."""

    def create(self, settings: Settings, context: SourceContext) -> IntentSource: ...


BUILT_IN: dict[str, str] = {
    "simulated": "dammrl_core.intent.simulated:PLUGIN",
    "pad": "dammrl_core.intent.pad.source:PLUGIN",
    "lsl": "dammrl_core.intent.lsl:PLUGIN",
}


def source_plugins() -> dict[str, str]:
    """Every installed intent source's name and who provides it."""
    return plugins.origins(ENTRY_POINTS, BUILT_IN)


def source_plugin(name: str) -> IntentSourcePlugin:
    """The intent source plug-in called ``name``."""
    source = "intent source (DAMMRL_INTENT_SOURCE)"
    return cast(IntentSourcePlugin, plugins.load(ENTRY_POINTS, BUILT_IN, name, source))
