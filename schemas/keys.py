"""One key expression per message type, under a namespace (default ``dammrl``).

Several stacks share a Zenoh network by using different namespaces.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from schemas.messages import (
    ComfortRating,
    DecisionRequest,
    EmergencyStop,
    EpisodeRecorded,
    EpisodeResult,
    GoalRefused,
    Health,
    Intent,
    IntentEvidence,
    JointCommand,
    Message,
    ModelChoice,
    RobotState,
    SensorSample,
    SessionControl,
    SignalChunk,
    StepEvent,
    TaskGoal,
)

DEFAULT_NAMESPACE = "dammrl"

TOPICS: dict[str, type[Message]] = {
    "robot/state": RobotState,
    "robot/command": JointCommand,
    "intent": Intent,
    "intent/request": DecisionRequest,
    "policy/model": ModelChoice,
    "controller/step": StepEvent,
    "task/goal": TaskGoal,
    "task/result": EpisodeResult,
    "task/refused": GoalRefused,
    "sensor/sample": SensorSample,
    "sensor/chunk": SignalChunk,
    "intent/evidence": IntentEvidence,
    "safety/stop": EmergencyStop,
    "session/comfort": ComfortRating,
    "session/control": SessionControl,
    "recorder/episode": EpisodeRecorded,
    "health/*": Health,  # one key per service: health/<service>
}


@dataclass(frozen=True)
class KeyLimits:
    """What a session lets in on one key. Rate: Zenoh drops a message that follows the
    last one from the same peer (link) on this key by less than ``1 / max_rate_hz`` s,
    before any subscriber sees it (its per-link ingress downsampling): a flooding peer
    is cut to the rate on its own link and never crowds out another peer's messages.
    Size: a larger payload is dropped and counted in Zenoh's callback, before it is
    copied. The stack's own messages stay far below both (a quarter of the size with
    every string and list at its bound; where a key has a rate, ten times the fastest rate
    the settings allow).

    ``max_rate_hz`` None: no rate rule. Zenoh's rule is a least interval, taken as the
    receiver works messages off: messages that wait together (a receiver or a sender
    the PC did not run for a few milliseconds, several put in one batch) are worked off
    microseconds apart, and all but the first are dropped, whatever the rate (bursts of
    five lost 4 of 5 at 10 kHz, 1 of 3 even at 1 MHz). The arm's loop streams wait so
    on a busy PC (beside two CPU hogs: states and commands lost, stale holds with no
    flood at all): they have none. A flood on them from their own role's certificate
    fills the receiver's inbox, and the arm holds (its commands stale), as it does for
    a silent controller. Health has a rule per service (one for ``health/*`` took the
    first of several services' Health sent back to back, and dropped the others)."""

    max_bytes: int
    max_rate_hz: float | None


LIMITS: dict[str, KeyLimits] = {
    # the arm's loop and the sensors: <= 1 kHz by the settings, at times back to back (no
    # rate rule: see KeyLimits). The size limits are the tightest with the margin below
    "robot/state": KeyLimits(2048, None),
    "robot/command": KeyLimits(2048, None),
    "sensor/sample": KeyLimits(1024, None),
    "controller/step": KeyLimits(2048, None),  # several steps may start in one tick
    # decisions and episodes: a few per second
    "intent": KeyLimits(4096, 1_000.0),
    "intent/request": KeyLimits(4096, 1_000.0),
    "policy/model": KeyLimits(4096, 1_000.0),
    "task/goal": KeyLimits(4096, 1_000.0),
    "task/result": KeyLimits(4096, 1_000.0),
    "task/refused": KeyLimits(2048, 1_000.0),
    "intent/evidence": KeyLimits(16_384, 100.0),  # <= 1024 features: ~9 kB
    # a wearable's raw stream: the intent service sends one chunk every 20 ms at most, of
    # at most CHUNK_BYTES (a 1 kHz, 8-channel stream: ~2 kB)
    "sensor/chunk": KeyLimits(32_768, 500.0),
    "session/comfort": KeyLimits(1024, 100.0),  # one per block
    "session/control": KeyLimits(1024, 100.0),  # a therapist's keys
    "recorder/episode": KeyLimits(2048, 1_000.0),  # one or two per episode
    "safety/stop": KeyLimits(1024, 1_000.0),  # per link: a flood never delays the console's
    "health/*": KeyLimits(32_768, 100.0),  # one a second per service: a rule per service
}
"""Per topic (relative to the namespace)."""
FOREIGN_LIMITS = KeyLimits(65_536, 1_000.0)
"""A key under the namespace that is no topic of the stack (kept by the recorder only)."""
MAX_MESSAGE_BYTES = 1 << 20
"""Zenoh's own bound: a larger message is dropped while it is reassembled (every session's
``transport/link/rx/max_message_size``), before any subscriber sees it."""


def downsampling(namespace: str, services: Iterable[str]) -> list[dict[str, object]]:
    """Zenoh's ingress downsampling for every key of the stack with a rate (per link: see
    KeyLimits); Health with a rule per service of ``services`` (a role may publish its
    own Health only)."""
    topics = [(t, limits) for t, limits in LIMITS.items() if t != "health/*"]
    topics += [(f"health/{service}", LIMITS["health/*"]) for service in services]
    rules = [
        {"key_expr": f"{namespace}/{topic}", "freq": limits.max_rate_hz}
        for topic, limits in topics
        if limits.max_rate_hz is not None
    ]
    return [{"id": "dammrl-limits", "flows": ["ingress"], "messages": ["put"], "rules": rules}]


def limits_of(namespace: str, key_expr: str) -> KeyLimits:
    """The limits of a concrete key under ``namespace``."""
    topic = key_expr.removeprefix(f"{namespace}/")
    if topic.startswith("health/"):
        topic = "health/*"
    return LIMITS.get(topic, FOREIGN_LIMITS)


def topic_of(message_type: type[Message]) -> str:
    for topic, cls in TOPICS.items():
        if cls is message_type:
            return topic
    raise KeyError(f"{message_type.__name__} has no topic")


def key(namespace: str, message_type: type[Message], service: str | None = None) -> str:
    """The key expression of ``message_type`` (``health/<service>`` for Health)."""
    topic = topic_of(message_type)
    if topic == "health/*":
        topic = f"health/{service or '*'}"
    return f"{namespace}/{topic}"


def type_of(namespace: str, key_expr: str) -> type[Message] | None:
    """The message type published on a concrete key, or None when it is not ours."""
    prefix = f"{namespace}/"
    if not key_expr.startswith(prefix):
        return None
    topic = key_expr[len(prefix) :]
    if topic.startswith("health/"):
        return Health
    return TOPICS.get(topic)
