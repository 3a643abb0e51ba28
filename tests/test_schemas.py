"""The schemas are the contract: round trips, rejections, key expressions, JSON Schema."""

from __future__ import annotations

import math
from typing import Any

import msgpack
import pytest

from schemas import (
    TOPICS,
    ComfortRating,
    DecisionRequest,
    DecodeError,
    EmergencyStop,
    EpisodeRecorded,
    EpisodeResult,
    GoalRefused,
    Header,
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
    decode,
    encode,
    key,
    type_of,
)

HEADER = Header(stamp_ns=1_700_000_000_000_000_000, seq=42, source="test")
J6 = (0.1, -0.2, 0.3, 1.2, 0.0, -0.5)
V3 = (0.4, -0.1, -0.2)

EXAMPLES: list[Message] = [
    RobotState(header=HEADER, episode=1, t_s=2.5, q_rad=J6, dq_rad_s=J6, tau_nm=J6,
               ee_pos_m=V3, ee_vel_m_s=V3, button_pressed=True, button_travel_m=0.004,
               holding=False),
    JointCommand(header=HEADER, episode=1, state_stamp_ns=5, q_ref_rad=J6, dq_ref_rad_s=J6,
                 tau_ff_nm=J6, kp_nm_per_rad=(400,) * 6, kd_nms_per_rad=(30,) * 6),
    DecisionRequest(header=HEADER, episode=1, seed=1, request=3, t_s=1.0, ee_pos_m=V3, goal_m=V3,
                    primary_axis=0, human_model=2),
    Intent(header=HEADER, episode=1, request=3, u_h=-1, human_model=2, radius_m=0.004,
           confidence=0.9, source="simulated", person=False, decision_s=0.4, correct=False),
    ModelChoice(header=HEADER, human_model=1, robot_model=3, radius_m=0.01,
                steps_m=(0.01, 0.03, 0.01), posterior=(0.7, 0.3)),
    StepEvent(header=HEADER, episode=1, index=4, t_s=1.0, start_s=1.05, trigger="event",
              u_h=1, radius_m=0.01, steps_m=V3, dx_m=V3, x_start_m=V3, subgoal_m=V3,
              goal_error_m=0.2, ik_compute_s=0.0001, ik_latency_s=0.05),
    TaskGoal(header=HEADER, episode=2, seed=7, start_m=V3, goal_m=V3, q_start_rad=J6),
    GoalRefused(header=HEADER, episode=2, reason="episode 2: the start posture not reached"),
    EpisodeResult(header=HEADER, episode=2, seed=7, trigger="fixed", model=(1, 3),
                  success=True, reached=True, outcome="success", reason="button pressed",
                  t_total_s=5.0, t_step_mean_s=None, final_error_m=0.01, n_osc=3,
                  n_osc_per_step=None, jerk_isj=1e4,
                  sparc=-2.5, ldlj=-8.0, human_error_rate=0.1, n_steps=40, n_decisions=20,
                  button_pressed=True, start_m=V3, goal_m=V3),
    SensorSample(header=HEADER, device_seq=9, raw=512, pressure_kpa=12.5),
    SignalChunk(header=HEADER, stream="ForearmEMG", rate_hz=1000.0,
                stamps_ns=[10**18 + k * 10**6 for k in range(20)],
                samples=[[0.01 * k] * 7 + [None if k == 3 else 0.5] for k in range(20)]),
    IntentEvidence(header=HEADER, episode=1, request=3, source="lsl", u_h=1, human_model=2,
                   confidence=0.93, onset_ns=10**18, decided_ns=10**18 + 10**9, duration_s=0.8,
                   windows=14,
                   features=(0.1,) * 32, acted=False, reason="confidence 0.70 < 0.75"),
    Health(header=HEADER, service="sim", state="ok", rejected={"dammrl/robot/command": 2},
           rates_hz={"dammrl/robot/state": 100.0}, uptime_s=3.0),
    EmergencyStop(header=HEADER, engaged=True, reason="the patient asked"),
    ComfortRating(header=HEADER, participant="P012", block="event", trial=7, rating=4,
                  asked_s=3.2),
    SessionControl(header=HEADER, episode=3, action="pause", who="T1", why="the patient coughs"),
    EpisodeRecorded(header=HEADER, episode=2, file="part-01.mcap", result_seq=7, states=512,
                    complete=False, missing="the robot state the result was decided from"),
]  # fmt: skip


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_every_message_round_trips(message: Message) -> None:
    assert decode(type(message), encode(message)) == message


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda m: type(m).__name__)
def test_wire_format_is_plain_msgpack_maps_and_lists(message: Message) -> None:
    plain = msgpack.unpackb(encode(message))
    assert isinstance(plain, dict) and plain["header"]["seq"] == 42

    def only_plain(value: Any) -> bool:
        if isinstance(value, dict):
            return all(isinstance(k, str) and only_plain(v) for k, v in value.items())
        if isinstance(value, list):
            return all(only_plain(v) for v in value)
        return value is None or isinstance(value, bool | int | float | str)

    assert only_plain(plain)


def _mutated(message: Message, **changes: Any) -> bytes:
    plain = msgpack.unpackb(encode(message))
    plain.update(changes)
    return bytes(msgpack.packb(plain))


STATE, COMMAND, INTENT = EXAMPLES[0], EXAMPLES[1], EXAMPLES[3]


def test_bytes_that_are_not_msgpack_are_refused() -> None:
    with pytest.raises(DecodeError, match="not msgpack"):
        decode(RobotState, b"\xc1\xc1 definitely not msgpack")


def test_msgpack_that_is_not_a_map_is_refused() -> None:
    with pytest.raises(DecodeError, match="expected a msgpack map"):
        decode(RobotState, bytes(msgpack.packb([1, 2, 3])))


@pytest.mark.parametrize(
    ("message", "changes", "complaint"),
    [
        (STATE, {"q_rad": [math.nan, 0, 0, 0, 0, 0]}, "finite"),
        (STATE, {"ee_pos_m": [math.inf, 0, 0]}, "finite"),
        (STATE, {"q_rad": [0, 0, 0]}, "q_rad"),
        (STATE, {"surprise": 1}, "Extra inputs"),
        (COMMAND, {"kp_nm_per_rad": [-1, 0, 0, 0, 0, 0]}, "greater than or equal"),
        (INTENT, {"u_h": 0}, "u_h"),
        (INTENT, {"source": ""}, "source"),
        (INTENT, {"human_model": 3}, "human_model"),
    ],
)
def test_invalid_content_is_refused_with_the_field_named(
    message: Message, changes: dict[str, Any], complaint: str
) -> None:
    with pytest.raises(DecodeError, match=complaint):
        decode(type(message), _mutated(message, **changes))


def test_each_type_has_one_key_under_the_namespace() -> None:
    assert key("dammrl", RobotState) == "dammrl/robot/state"
    assert key("lab2", Health, "sim") == "lab2/health/sim"
    assert type_of("lab2", "lab2/health/sim") is Health
    assert type_of("dammrl", "dammrl/robot/command") is JointCommand
    assert type_of("dammrl", "other/robot/state") is None
    assert len(set(TOPICS.values())) == len(TOPICS)


def test_json_schema_exists_for_every_message() -> None:
    for message_type in TOPICS.values():
        schema = message_type.model_json_schema()
        assert schema["additionalProperties"] is False
        assert "header" in schema["properties"]


def test_every_topic_has_an_example_here() -> None:
    """The round trips above, and the stack's fuzzer, cover every message type."""
    assert {type(m) for m in EXAMPLES} == set(TOPICS.values())


def test_an_episode_result_carries_exactly_the_metrics_of_a_reach() -> None:
    """One definition of the episode metrics: ReachMetrics (the library); EpisodeResult
    carries exactly its fields and what identifies the run, so a metric added to one is
    missing from the other only until this test runs."""
    from schemas import EpisodeResult
    from services.common.convert import IDENTIFIES_A_RUN, LOCATES_ITS_END, METRICS

    others = {"header", "episode", *IDENTIFIES_A_RUN, *LOCATES_ITS_END}
    carried = set(EpisodeResult.model_fields) - others
    assert carried == set(METRICS)


def test_an_intent_recorded_before_person_existed_reads_as_the_pad_was_a_person() -> None:
    from schemas import Intent, decode

    old = msgpack.packb(INTENT.model_dump(exclude={"person"}) | {"source": "sensor"})
    assert decode(Intent, old).person
