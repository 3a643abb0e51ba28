"""The controller's settings: one class, environment prefix ``DAMMRL_CONTROLLER_`` (read by the
controller service and by every in-process composition)."""

from __future__ import annotations

from typing import Annotated, Literal, Self

from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from dammrl_core.errors import ConfigurationError
from dammrl_core.ik import MAX_LATENCY_SCALE, IKSolverName, LatencyMode
from dammrl_core.settings import PerJointDamping, PerJointGain, Settings, ordered
from dammrl_core.task import TaskSettings, scene_layout

Trigger = Literal["event", "fixed"]
Feedforward = Literal["inverse_dynamics", "resolved_acceleration"]
_Weight = Annotated[float, Field(gt=0, le=100)]
# the workspace box: in front of the shoulder (x, never behind its plane, towards the
# person), within the reference arm's reach of 0.74 m
REACH_M = 0.8
_X = Annotated[float, Field(ge=0.05, le=REACH_M)]
_Y = Annotated[float, Field(ge=-REACH_M, le=REACH_M)]
_Z = Annotated[float, Field(ge=-REACH_M, le=REACH_M)]


class ControllerSettings(Settings):
    """How micro-steps are planned, triggered, solved and turned into joint commands."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_CONTROLLER_")

    trigger: Trigger = "event"
    """'event': next step when ||x - x_m|| <= eps and dV/dt <= 0; 'fixed': on a timer."""
    fixed_period_s: float = Field(0.1, ge=0.01, le=5.0)
    """Timer period of the fixed-frequency baseline [s]."""
    fixed_step_from: Literal["measured", "subgoal"] = "measured"
    """Where a fixed-rate step starts: the measured end-effector position, or the last
    planned subgoal, x^(m+1) = x^(m) + dx, the paper's chain that can run ahead of the arm."""
    fixed_replan_while_pending: bool = False
    """Whether a timer tick plans a step while the last IK solve is still running (the
    paper's "premature IK update": solves overlap and each starts when ready), or skips."""
    fixed_decisions: Literal["latest", "fresh"] = "latest"
    """Fixed rate: each tick re-uses the human's latest decision (the paper), or takes a
    fresh one and waits for it (one decision per step, as the event trigger does)."""
    control_rate_hz: float = Field(100.0, ge=20, le=1000)
    """Rate at which the reference is sampled into joint commands and the trigger checked."""
    primary_axis: Literal[0, 1, 2] = 0
    """Task axis driven by the human's binary command (0 = x, 1 = y, 2 = z)."""
    orthogonal_deadband: bool = True
    """Skip an orthogonal step when |e| <= delta/2 (the step would increase |e|)."""
    lyapunov_weights: tuple[_Weight, _Weight, _Weight] = (1.0, 1.0, 1.0)
    """Diagonal of W in V = 1/2 e^T W e, e = x_m - x (each above 0, at most 100: W must be
    positive definite)."""

    ik_solver: IKSolverName = "pinocchio"
    """'pinocchio' (damped least squares, fast) or 'ikpy' (bounded optimisation, the paper's)."""
    ik_latency: LatencyMode = "model"
    """How IK compute time enters simulated time: drawn from a fitted lognormal ('model'),
    the processor time of each solve here ('measured': the paper's mechanism, reproduced by
    replaying the latencies a run spent), the time each solve's work took on the reference
    machine ('reference': the mechanism without this computer's speed), or 0 ('zero')."""
    ik_latency_profile: IKSolverName = "ikpy"
    """Whose fitted compute-time distribution 'model' draws from. Default: the paper's solver,
    so results carry the paper's timing whichever solver computes the joint solution."""
    ik_latency_median_s: float | None = Field(None, gt=0, le=5)
    """Override of the latency model's median [s]."""
    ik_latency_sigma: float | None = Field(None, ge=0, le=3)
    """Override of the latency model's log-standard deviation."""
    ik_latency_scale: float = Field(1.0, gt=0, le=MAX_LATENCY_SCALE)
    """Every IK latency times this (0-100, exclusive of 0): a computer this many times
    slower than the one the latency stands for (how results depend on solve time)."""
    calibration_correction: bool = True
    """Aim each step's IK at the subgoal minus the measured end-effector's offset from the
    nominal forward kinematics: without it, a calibration error of a few millimetres puts
    every step beside its subgoal and a small admission sphere is never entered. (Zero when
    the end-effector position is itself computed from the joint angles.)"""
    ik_accept_error_m: float = Field(1e-3, gt=0, le=0.01)
    """An IK solution farther than this from its target is a failure [m] (at most 10 mm:
    the smallest micro-step)."""
    max_joint_step_rad: float = Field(0.5, gt=0, le=1.0)
    """IK searches within the seed +- this per joint, so a micro-step never jumps [rad]."""

    peak_speed_m_per_s: float = Field(0.2, gt=0, le=1.0)
    """Peak Cartesian speed of a micro-step's minimum-jerk profile [m/s]."""
    joint_speed_fraction: float = Field(0.5, gt=0, le=1)
    """Peak joint speed as a fraction of the URDF velocity limit."""
    min_segment_s: float = Field(0.08, ge=0.01, le=5.0)
    """Shortest duration of one micro-step segment [s]."""
    kp: PerJointGain = (400.0, 400.0, 200.0, 200.0, 50.0, 50.0)
    """Joint stiffness [N m/rad] (0-2000 each: the sim's default maximum; the real arm's
    is 1000)."""
    kd: PerJointDamping = (30.0, 30.0, 12.0, 12.0, 1.5, 1.5)
    """Joint damping gains [N m s/rad] (0-200 each)."""
    feedforward: Feedforward = "inverse_dynamics"
    """'inverse_dynamics': RNEA along the joint reference; 'resolved_acceleration': the
    paper's J# (xdd - Jd qd) + (I - J# J) z with a joint-limit-avoiding null-space term."""
    null_space_gain: float = Field(2.0, ge=0, le=50)
    """Joint-limit avoidance acceleration at a limit, applied in the null space [rad/s^2]."""

    joint_limit_margin_rad: float = Field(0.02, ge=0, le=0.3)
    """IK targets stay this far inside the joint limits [rad]."""
    workspace_min_m: tuple[_X, _Y, _Z] = (0.1, -0.45, -0.235)
    """Lower corner of the allowed end-effector box in the task frame [m]: x 0.05-0.8 (in
    front of the shoulder), y and z -0.8-0.8 (the arm's reach), each below its upper
    corner; its floor (z) at least a fingertip's radius above the table
    (``DAMMRL_TASK_TABLE_TOP_Z_M``)."""
    workspace_max_m: tuple[_X, _Y, _Z] = (0.72, 0.45, 0.20)
    """Upper corner of the allowed end-effector box [m] (ranges as the lower corner's)."""
    trigger_timeout_s: float = Field(3.0, ge=0.1, le=60)
    """A step whose trigger has not fired after this long ends in a hold [s]."""

    # --- the node (bus) ---
    state_stale_s: float = Field(0.1, ge=0.02, le=1.0)
    """No RobotState for this long: stop stepping and hold the last reference [s] (0.02-1
    s: the watchdog cannot be switched off by a large number)."""
    policy_wait_s: float = Field(20.0, ge=0, le=600)
    """How long the first episode waits for the policy's first ModelChoice and for the
    human (intent) service to be alive [s]."""
    request_resend_s: float = Field(2.0, gt=0, le=60)
    """An unanswered decision request is sent again this often, so a human (intent)
    service that joined late or restarted answers it [s]."""
    choice_wait_s: float = Field(0.2, gt=0, le=10)
    """How long the human's answer waits for the policy's choice of the same request [s]."""
    outcome_hold_s: float = Field(0.0, ge=0, le=30)
    """Between a reach's result and the next reach's goal [s] (0-30): the participant
    display shows the outcome meanwhile (a session holds it 2 s by default)."""
    first_reach_held_by: str = Field("", max_length=200, exclude=True)
    """Who holds the first reach back until their resume (a session: until its console,
    stop and display are up); empty: it begins once the services are. A run's, not a
    reach's: left out of the settings' dump (a study's search fingerprint, a recording's
    settings), as it decides no result."""
    human_model: int = Field(1, ge=1, le=2)
    """Model used until the policy's first ModelChoice arrives (i: 1 = E_big)."""
    robot_model: int = Field(1, ge=1, le=8)
    """Model used until the policy's first ModelChoice arrives (j: step vector)."""

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        """A box whose lower corner lies below its upper corner on every axis."""
        ordered(self, "workspace_min_m", "workspace_max_m")
        return self


def check_workspace(controller: ControllerSettings, task: TaskSettings) -> None:
    """ConfigurationError unless the workspace's floor keeps the fingertip on the table
    (its centre at least a fingertip's radius above the table top): the table margin the
    box exists for. The controller and every composition check it before a reach."""
    floor = task.table_top_z_m + scene_layout(task).fingertip_radius_m
    given = controller.workspace_min_m[2]
    if given < floor - 1e-9:
        raise ConfigurationError(
            f"invalid setting: DAMMRL_CONTROLLER_WORKSPACE_MIN_M[2]={given:g}: outside its "
            f"range [{floor:g}, {REACH_M:g}] (the workspace's floor keeps the fingertip above "
            f"the table, DAMMRL_TASK_TABLE_TOP_Z_M={task.table_top_z_m:g})"
        )
