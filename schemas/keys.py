"""One key expression per message type, under a namespace (default ``dammrl``).

Several stacks share a Zenoh network by using different namespaces.
"""

from __future__ import annotations

from dataclasses import dataclass

from schemas.messages import (
    ComfortRating,
    DecisionRequest,
    EmergencyStop,
    EpisodeRecorded,
    EpisodeResult,
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
    every string and list at its bound; ten times the fastest rate the settings allow)."""

    max_bytes: int
    max_rate_hz: float


LIMITS: dict[str, KeyLimits] = {
    # the arm's loop and the sensors: <= 1 kHz by the settings, at times back to back. The
    # size limits are the tightest with the margin below: they bound what a peer holding a
    # role's key can make every receiver read (size x rate, ~20 MB/s per key)
    "robot/state": KeyLimits(2048, 10_000.0),
    "robot/command": KeyLimits(2048, 10_000.0),
    "sensor/sample": KeyLimits(1024, 10_000.0),
    "controller/step": KeyLimits(2048, 10_000.0),  # several steps may start in one tick
    # decisions and episodes: a few per second
    "intent": KeyLimits(4096, 1_000.0),
    "intent/request": KeyLimits(4096, 1_000.0),
    "policy/model": KeyLimits(4096, 1_000.0),
    "task/goal": KeyLimits(4096, 1_000.0),
    "task/result": KeyLimits(4096, 1_000.0),
    "intent/evidence": KeyLimits(16_384, 100.0),  # <= 1024 features: ~9 kB
    # a wearable's raw stream: the intent service sends one chunk every 20 ms at most, of
    # at most CHUNK_BYTES (a 1 kHz, 8-channel stream: ~2 kB)
    "sensor/chunk": KeyLimits(32_768, 500.0),
    "session/comfort": KeyLimits(1024, 100.0),  # one per block
    "session/control": KeyLimits(1024, 100.0),  # a therapist's keys
    "recorder/episode": KeyLimits(2048, 1_000.0),  # one or two per episode
    "safety/stop": KeyLimits(1024, 1_000.0),  # per link: a flood never delays the console's
    "health/*": KeyLimits(32_768, 100.0),  # one a second per service
}
"""Per topic (relative to the namespace)."""
FOREIGN_LIMITS = KeyLimits(65_536, 1_000.0)
"""A key under the namespace that is no topic of the stack (kept by the recorder only)."""
MAX_MESSAGE_BYTES = 1 << 20
"""Zenoh's own bound: a larger message is dropped while it is reassembled (every session's
``transport/link/rx/max_message_size``), before any subscriber sees it."""


def downsampling(namespace: str) -> list[dict[str, object]]:
    """Zenoh's ingress downsampling for every key of the stack (per link: see KeyLimits)."""
    rules = [
        {"key_expr": f"{namespace}/{topic}", "freq": limits.max_rate_hz}
        for topic, limits in LIMITS.items()
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
