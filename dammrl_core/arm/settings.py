"""The real arm's settings, whatever drives it: one class, environment prefix ``DAMMRL_ARM_``
(the arm's description stays ``DAMMRL_ROBOT_*``; the driver's own settings, such as its
port and calibration file, have the driver's prefix, e.g. ``DAMMRL_DYNAMIXEL_``)."""

from __future__ import annotations

from dataclasses import replace
from typing import Literal, Self

import numpy as np
from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from dammrl_core.robot import RobotDescription
from dammrl_core.settings import PerJointDamping, PerJointGain, Settings


class ArmSettings(Settings):
    """The arm's limits for a person attached, its holds, stop and start."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_ARM_")

    driver: str = Field("dynamixel", min_length=1)
    """The arm's driver: a built-in (``dynamixel``) or one an installed package registers
    under the entry-point group ``dammrl.arm_drivers`` (``dammrl robot drivers`` lists them)."""
    loop_rate_hz: float = Field(100.0, ge=10, le=1000)
    """The loop: one read, one write and one RobotState per period [Hz]."""

    # ---- limits with a person attached (never above the URDF's) --------------------------
    torque_fraction: float = Field(0.6, gt=0, le=1.0)
    """Each servo's torque is limited (its goal current) to this fraction of the URDF's
    effort limit; commands asking for more feed-forward are rejected."""
    speed_fraction: float = Field(0.9, gt=0, le=1.0)
    """References move, and measured joints may move, at most this fraction of the URDF's
    velocity limits (the sim allows 1.0)."""
    overspeed_stop_fraction: float = Field(1.0, gt=0, le=1.0)
    """A measured joint speed above this fraction of the URDF's velocity limit stops the
    arm (above ``speed_fraction``: references stay below it, the arm's own motion may
    overshoot them a little)."""
    limit_tolerance_rad: float = Field(0.03, ge=0, le=0.2)
    """q_ref may exceed the arm's joint limits by this much before rejection; a measured
    joint beyond its limit by this much stops the arm [rad]."""
    max_kp_nm_per_rad: float = Field(1000.0, gt=0, le=10_000)
    max_kd_nms_per_rad: float = Field(100.0, gt=0, le=1_000)
    max_relative_target_rad: float = Field(0.15, gt=0, le=1.0)
    """The applied q_ref stays this close to the measured posture, per joint [rad]."""

    # ---- holds, the stop, the start -----------------------------------------------------
    command_stale_s: float = Field(0.1, ge=0.02, le=1.0)
    """No valid command for this long: hold where the arm is [s] (0.02-1 s: the watchdog
    cannot be switched off by a large number)."""
    command_max_age_s: float = Field(0.05, gt=0, le=1.0)
    """A command must answer a state published at most this long ago [s]."""
    hold_kp_nm_per_rad: PerJointGain = (300.0, 300.0, 150.0, 150.0, 40.0, 40.0)
    """Stiffness of a hold before any command (then: the last command's) [N m/rad]."""
    hold_kd_nms_per_rad: PerJointDamping = (25.0, 25.0, 10.0, 10.0, 1.5, 1.5)
    stop_action: Literal["hold", "torque_off"] = "hold"
    """What an emergency stop or a fault does: hold where the arm is with the stop gains
    and gravity compensation (the arm does not fall on the person), or torque off."""
    stop_kp_nm_per_rad: PerJointGain = (120.0, 120.0, 60.0, 60.0, 15.0, 15.0)
    """Stiffness of a stop: low, so a person can move the arm against it [N m/rad]."""
    stop_kd_nms_per_rad: PerJointDamping = (20.0, 20.0, 8.0, 8.0, 1.0, 1.0)
    soft_start_s: float = Field(1.0, ge=0, le=10)
    """After torque on, the stiffness ramps from ``soft_start_fraction`` to full over this
    [s] (the damping is full from the torque-on: a sagging joint stays slow)."""
    soft_start_fraction: float = Field(0.1, ge=0, le=1)
    homing_speed_rad_s: float = Field(0.3, gt=0, le=1.0)
    """A new episode moves the arm to its start posture at most this fast [rad/s]."""
    rest_speed_rad_s: float = Field(0.05, gt=0, le=1.0)
    """An episode starts (homing ends) once no joint moves faster [rad/s]."""
    homing_tolerance_rad: float = Field(0.02, gt=0, le=0.2)
    homing_timeout_s: float = Field(5.0, gt=0, le=60)
    """Not at rest at the start posture this long after the move's end (blocked by the
    table, or held by the person): the episode is refused and the arm holds where it is."""
    max_restarts: int = Field(2, ge=0, le=10)
    """A drive whose overload cut its torque is restarted and put back holding where its
    joint is, at most this many times per run; then it stays off (support the arm)."""
    max_bus_errors: int = Field(3, ge=1, le=100)
    """Consecutive failed bus cycles before a fault (the servos hold their last goal in
    between) [-]."""
    reconnect_s: float = Field(1.0, ge=0.1, le=60)
    """After a bus fault, try to reconnect this often (an unplugged cable) [s]."""

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        """Holds and stops no stiffer than a command may be; a watchdog of two periods."""
        for name in ("hold_kp_nm_per_rad", "stop_kp_nm_per_rad"):
            if max(getattr(self, name)) > self.max_kp_nm_per_rad:
                raise ValueError(f"{name} must not exceed max_kp_nm_per_rad")
        for name in ("hold_kd_nms_per_rad", "stop_kd_nms_per_rad"):
            if max(getattr(self, name)) > self.max_kd_nms_per_rad:
                raise ValueError(f"{name} must not exceed max_kd_nms_per_rad")
        if self.speed_fraction >= self.overspeed_stop_fraction:
            raise ValueError("speed_fraction must stay below overspeed_stop_fraction")
        if self.command_stale_s < 2 / self.loop_rate_hz:
            raise ValueError("command_stale_s must span at least two loop periods")
        return self


def arm_limits(robot: RobotDescription, q_limits: tuple[np.ndarray, np.ndarray],
               settings: ArmSettings) -> RobotDescription:  # fmt: skip
    """The limits this arm runs under with a person attached: its calibration's joint
    limits ``q_limits`` (inside the URDF's) and fractions of the URDF's speed and effort."""
    return replace(
        robot,
        q_min=q_limits[0],
        q_max=q_limits[1],
        dq_max=robot.dq_max * settings.speed_fraction,
        tau_max=robot.tau_max * settings.torque_fraction,
    )
