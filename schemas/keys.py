"""One key expression per message type, under a namespace (default ``dammrl``).

Several stacks share a Zenoh network by using different namespaces.
"""

from __future__ import annotations

from schemas.messages import (
    DecisionRequest,
    EmergencyStop,
    EpisodeResult,
    Health,
    Intent,
    JointCommand,
    Message,
    ModelChoice,
    RobotState,
    SensorSample,
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
    "safety/stop": EmergencyStop,
    "health/*": Health,  # one key per service: health/<service>
}


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
