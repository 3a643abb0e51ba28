"""Message models, codec and key expressions of the bus: the contract between services."""

from schemas.codec import DecodeError, decode, encode
from schemas.keys import DEFAULT_NAMESPACE, TOPICS, key, type_of
from schemas.messages import (
    ComfortRating,
    DecisionRequest,
    EmergencyStop,
    EpisodeResult,
    Header,
    Health,
    Intent,
    IntentEvidence,
    JointCommand,
    Message,
    ModelChoice,
    RobotState,
    SensorSample,
    SignalChunk,
    StepEvent,
    TaskGoal,
)

__all__ = [
    "DEFAULT_NAMESPACE",
    "TOPICS",
    "ComfortRating",
    "DecisionRequest",
    "DecodeError",
    "EmergencyStop",
    "EpisodeResult",
    "Header",
    "Health",
    "Intent",
    "IntentEvidence",
    "JointCommand",
    "Message",
    "ModelChoice",
    "RobotState",
    "SensorSample",
    "SignalChunk",
    "StepEvent",
    "TaskGoal",
    "decode",
    "encode",
    "key",
    "type_of",
]
