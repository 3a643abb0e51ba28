"""Conversions between the library's numpy dataclasses and the bus messages (both ways), so
every message is built typed, in one place."""

from __future__ import annotations

from typing import Any

import numpy as np

from dammrl_core import state as core
from dammrl_core.metrics import ReachMetrics
from schemas import messages as wire

IDENTIFIES_A_RUN = ("trigger", "model", "seed", "start_m", "goal_m")
"""The fields of an EpisodeResult beyond the metrics (and its header and episode)..."""
LOCATES_ITS_END = ("last_state_stamp_ns",)
"""... and the one that says where its reach ends in the record."""


def _floats(array: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in array)


def state_message(
    header: wire.Header,
    state: core.RobotState,
    episode: int,
    holding: bool,
    q_ref: np.ndarray | None = None,
    command_answers_ns: int | None = None,
) -> wire.RobotState:
    return wire.RobotState(
        header=header,
        q_ref_applied_rad=None if q_ref is None else _floats(q_ref),
        command_answers_ns=command_answers_ns,
        episode=episode,
        t_s=state.t_s,
        q_rad=_floats(state.q),
        dq_rad_s=_floats(state.dq),
        tau_nm=_floats(state.tau),
        ee_pos_m=_floats(state.ee_pos),
        ee_vel_m_s=_floats(state.ee_vel),
        button_pressed=state.button_pressed,
        button_travel_m=state.button_travel_m,
        holding=holding,
    )


def robot_state(message: wire.RobotState) -> core.RobotState:
    return core.RobotState(
        t_s=message.t_s,
        q=np.array(message.q_rad),
        dq=np.array(message.dq_rad_s),
        tau=np.array(message.tau_nm),
        ee_pos=np.array(message.ee_pos_m),
        ee_vel=np.array(message.ee_vel_m_s),
        button_pressed=message.button_pressed,
        button_travel_m=message.button_travel_m,
    )


def command_message(
    header: wire.Header, command: core.JointCommand, episode: int, state_stamp_ns: int
) -> wire.JointCommand:
    return wire.JointCommand(
        header=header,
        episode=episode,
        state_stamp_ns=state_stamp_ns,
        q_ref_rad=_floats(command.q_ref),
        dq_ref_rad_s=_floats(command.dq_ref),
        tau_ff_nm=_floats(command.tau_ff),
        kp_nm_per_rad=_floats(command.kp),
        kd_nms_per_rad=_floats(command.kd),
    )


def joint_command(message: wire.JointCommand) -> core.JointCommand:
    return core.JointCommand(
        q_ref=np.array(message.q_ref_rad),
        dq_ref=np.array(message.dq_ref_rad_s),
        tau_ff=np.array(message.tau_ff_nm),
        kp=np.array(message.kp_nm_per_rad),
        kd=np.array(message.kd_nms_per_rad),
    )


def step_message(header: wire.Header, step: core.StepEvent, episode: int) -> wire.StepEvent:
    return wire.StepEvent(
        header=header,
        episode=episode,
        index=step.index,
        t_s=step.t_s,
        start_s=step.start_s,
        trigger=step.trigger,
        u_h=step.u_h,
        radius_m=step.radius_m,
        steps_m=_floats(step.steps_m),
        dx_m=_floats(step.dx),
        x_start_m=_floats(step.x_start),
        subgoal_m=_floats(step.subgoal),
        goal_error_m=step.goal_error_m,
        ik_compute_s=step.ik_compute_s,
        ik_latency_s=step.ik_latency_s,
    )


def episode_result(
    header: wire.Header,
    episode: int,
    summary: dict[str, Any],
    last_state_stamp_ns: int | None = None,
) -> wire.EpisodeResult:
    """An episode's result from ``metrics.episode_summary`` (the metrics of ReachMetrics,
    one definition, and what identifies the run); ``last_state_stamp_ns``: the header
    stamp of the last robot state the reach took in."""
    return wire.EpisodeResult.model_validate(
        summary
        | {"header": header, "episode": episode, "reason": str(summary["reason"])[:500],
           "last_state_stamp_ns": last_state_stamp_ns}
    )  # fmt: skip


def goal_refused(header: wire.Header, episode: int, reason: str) -> wire.GoalRefused:
    """The arm's refusal of an episode it can never begin (its reason cut to the bound)."""
    return wire.GoalRefused(header=header, episode=episode, reason=reason[:500])


METRICS = tuple(ReachMetrics.__dataclass_fields__)
"""The metric fields an EpisodeResult carries (``tests/test_schemas.py`` checks they are
exactly ReachMetrics', so a metric added to one is in the other)."""
