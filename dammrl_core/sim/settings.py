"""The simulated arm's settings: one class, environment prefix ``DAMMRL_SIM_`` (the sim service
and every in-process composition)."""

from __future__ import annotations

from typing import Self

from pydantic import BaseModel, Field, model_validator
from pydantic_settings import SettingsConfigDict

from dammrl_core.settings import (
    FINITE,
    MIN_DAMPING_NMS_PER_RAD,
    MIN_STIFFNESS_NM_PER_RAD,
    Settings,
    at_least,
    ordered,
)


class DomainRandomization(BaseModel):
    """Seeded perturbations of the simulated arm (off by default)."""

    model_config = FINITE

    enabled: bool = False
    """Randomise the arm (off: the nominal arm)."""
    mass_scale: float = Field(0.15, ge=0, lt=1)
    """Link masses (and inertias) scaled by U(1 - s, 1 + s)."""
    damping_scale: float = Field(0.3, ge=0, lt=1)
    """Joint damping scaled by U(1 - s, 1 + s)."""
    friction_max_nm: float = Field(0.3, ge=0, le=5)
    """Joint dry friction drawn from U(0, max) [N m]."""
    link_length_scale: float = Field(0.02, ge=0, lt=0.2)
    """Kinematics: each link's offset from its parent (its length) scaled by U(1 - s,
    1 + s). The controller's IK and dynamics keep the nominal model, as on a real arm whose
    calibration is imperfect."""
    joint_offset_rad: float = Field(0.005, ge=0, le=0.1)
    """Kinematics: encoder zero offsets drawn from U(-max, max) [rad]: the reported joint
    angle is the true one plus its offset, and the joint servo holds the reported angle."""
    q_noise_rad: float = Field(2e-4, ge=0, le=0.05)
    """Standard deviation of joint-position sensor noise [rad]."""
    dq_noise_rad_per_s: float = Field(2e-3, ge=0, le=0.5)
    """Standard deviation of joint-velocity sensor noise [rad/s]."""
    ee_noise_m: float = Field(2e-4, ge=0, le=0.01)
    """Standard deviation of end-effector position noise [m]."""
    ee_vel_noise_m_per_s: float = Field(1e-3, ge=0, le=0.1)
    """Standard deviation of end-effector velocity noise [m/s]: the joint-velocity noise
    through the arm's Jacobian (0.5-1.0 mm/s per axis at the start postures), as an arm
    that reports J(q) dq would measure it. The trigger's dV/dt <= 0 test reads it."""


class SimSettings(Settings):
    """The simulated arm's physics (the arm itself is ``DAMMRL_ROBOT_*``, the table
    ``DAMMRL_TASK_*``)."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_SIM_")

    timestep_s: float = Field(0.001, ge=2e-4, le=0.005)
    """Physics step [s] (0.2-5 ms: shorter steps cannot keep real time on a PC)."""
    button_press_travel_m: float = Field(0.003, gt=0, le=0.01)
    """Cap travel at which the button counts as pressed [m]."""
    randomization: DomainRandomization = DomainRandomization()

    # --- the node (bus) ---
    state_rate_hz: float = Field(100.0, ge=50, le=1000)
    """RobotState publication rate; also the rate at which commands are taken up [Hz]."""
    command_stale_s: float = Field(0.1, ge=0.02, le=1.0)
    """No valid command for this long: hold position (gravity compensation + damping)
    [s] (0.02-1 s: the watchdog cannot be switched off by a large number)."""
    hold_kp_nm_per_rad: float = Field(100.0, ge=MIN_STIFFNESS_NM_PER_RAD, le=2000)
    """Stiffness of a hold before any command arrived (then: the last command's) [N m/rad]
    (5-2000: softer is no hold)."""
    hold_kd_nms_per_rad: float = Field(10.0, ge=MIN_DAMPING_NMS_PER_RAD, le=200)
    """Damping of a hold before any command arrived (then: the last command's) [N m s/rad]."""
    max_kp_nm_per_rad: float = Field(2000.0, gt=0, le=10_000)
    """Commands asking for more stiffness are rejected [N m/rad]."""
    max_kd_nms_per_rad: float = Field(200.0, gt=0, le=1_000)
    """Commands asking for more damping are rejected [N m s/rad]."""
    limit_tolerance_rad: float = Field(0.05, ge=0, le=0.5)
    """Commanded q_ref may exceed the joint limits by this much before rejection [rad]."""
    max_relative_target_rad: float = Field(0.15, gt=0, le=1.0)
    """The applied q_ref stays this close to the measured posture, per joint [rad] (the
    controller's own references stay within 0.054 rad)."""
    reference_speed_fraction: float = Field(0.9, gt=0, le=1.0)
    """The applied reference moves, and asks to move, at most this fraction of the URDF
    velocity limits (the controller's own stay within 0.7 of them)."""
    speed_governor_fraction: float = Field(0.95, gt=0, le=1.0)
    """The simulated drives give no torque that would speed a joint past this fraction of
    its URDF velocity limit (checked at every physics step, on the bus only)."""
    overspeed_stop_fraction: float = Field(1.0, gt=0, le=1.0)
    """A measured joint speed above this fraction of the URDF velocity limit, or a joint
    beyond its limits by ``limit_tolerance_rad``, stops the arm (a fault: it holds, takes
    no command and refuses new episodes until the service restarts), as on the real arm."""
    rest_speed_rad_s: float = Field(0.05, gt=0, le=1.0)
    """A new episode (TaskGoal) resets the arm only when no joint moves faster [rad/s]."""
    command_max_age_s: float = Field(0.05, gt=0, le=1.0)
    """A command must answer a state published at most this long ago (in state periods;
    in lockstep the last state); older or out-of-order answers are rejected [s]."""

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        """A hold no stiffer than a command may be; a watchdog longer than two periods."""
        ordered(self, "hold_kp_nm_per_rad", "max_kp_nm_per_rad", strict=False)
        ordered(self, "hold_kd_nms_per_rad", "max_kd_nms_per_rad", strict=False)
        ordered(self, "reference_speed_fraction", "speed_governor_fraction", strict=False)
        ordered(self, "speed_governor_fraction", "overspeed_stop_fraction")
        at_least(self, "command_stale_s", 2 / self.state_rate_hz,
                 f"two periods of state_rate_hz={self.state_rate_hz:g}")  # fmt: skip
        return self
