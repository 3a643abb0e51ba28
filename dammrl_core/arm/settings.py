"""The real arm's settings, whatever drives it: one class, environment prefix ``DAMMRL_ARM_``
(the arm's description stays ``DAMMRL_ROBOT_*``; the driver's own settings, such as its
port and calibration file, have the driver's prefix, e.g. ``DAMMRL_DYNAMIXEL_``)."""

from __future__ import annotations

from dataclasses import replace
from typing import Literal, Self

import numpy as np
from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from dammrl_core.errors import ConfigurationError
from dammrl_core.robot import RobotDescription
from dammrl_core.settings import PerJointDamping, PerJointGain, Settings, at_least, ordered

MIN_TORQUE_FRACTION = 0.3
"""The reference arm's own weight needs 0.17 of the shoulder's effort limit at worst
(0.26 with ``WEIGHT_MARGIN``)."""
WEIGHT_MARGIN = 1.5
"""The torque limits must hold this many times the arm's own weight (the person's arm adds
to it: the margin is for them and for the model's error)."""


class ArmSettings(Settings):
    """The arm's limits for a person attached, its holds, stop and start."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_ARM_")

    driver: str = Field("dynamixel", min_length=1)
    """The arm's driver: a built-in (``dynamixel``) or one an installed package registers
    under the entry-point group ``dammrl.arm_drivers`` (``dammrl robot drivers`` lists them)."""
    loop_rate_hz: float = Field(100.0, ge=10, le=1000)
    """The loop: one read, one write and one RobotState per period [Hz]."""

    # ---- limits with a person attached (never above the URDF's) --------------------------
    torque_fraction: float = Field(0.6, ge=MIN_TORQUE_FRACTION, le=1.0)
    """Each servo's torque is limited (its goal current) to this fraction of the URDF's
    effort limit; commands asking for more feed-forward are rejected (0.3-1: less cannot
    hold the arm's own weight, ``holds_its_weight``)."""
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
    """Commands asking for more stiffness are rejected [N m/rad]."""
    max_kd_nms_per_rad: float = Field(100.0, gt=0, le=1_000)
    """Commands asking for more damping are rejected [N m s/rad]."""
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
    """Damping of that hold [N m s/rad]."""
    stop_action: Literal["hold", "torque_off"] = "hold"
    """What an emergency stop or a fault does: hold where the arm is with the stop gains
    and gravity compensation (the arm does not fall on the person), or torque off."""
    stop_kp_nm_per_rad: PerJointGain = (120.0, 120.0, 60.0, 60.0, 15.0, 15.0)
    """Stiffness of a stop: low, so a person can move the arm against it [N m/rad]."""
    stop_kd_nms_per_rad: PerJointDamping = (20.0, 20.0, 8.0, 8.0, 1.0, 1.0)
    """Damping of a stop [N m s/rad]."""
    soft_start_s: float = Field(1.0, ge=0.2, le=10)
    """After torque on, the gains ramp from ``soft_start_fraction`` to full over this [s]
    (0.2-10 s: no ramp at all would jump to the reference at full stiffness)."""
    soft_start_fraction: float = Field(0.1, ge=0.05, le=1)
    """Where the ramp starts, a fraction of the full gains (0.05-1: at 0 the arm would
    start with no stiffness at all)."""
    homing_speed_rad_s: float = Field(0.3, gt=0, le=1.0)
    """A new episode moves the arm to its start posture at most this fast [rad/s]."""
    rest_speed_rad_s: float = Field(0.05, gt=0, le=1.0)
    """An episode starts (homing ends) once no joint moves faster [rad/s]."""
    homing_tolerance_rad: float = Field(0.02, gt=0, le=0.2)
    """Homing has arrived once every joint is this close to the start posture [rad]."""
    homing_timeout_s: float = Field(5.0, gt=0, le=60)
    """Not at rest at the start posture this long after the move's end (blocked by the
    table, or held by the person): the episode is refused and the arm holds where it is."""
    max_restarts: int = Field(2, ge=1, le=10)
    """A drive whose overload cut its torque is restarted and put back holding where its
    joint is, at most this many times per run; then it stays off (support the arm). 1-10:
    with none, the first overload would leave the joint falling."""
    max_bus_errors: int = Field(3, ge=1, le=100)
    """Consecutive failed bus cycles before a fault (the servos hold their last goal in
    between) [-]."""
    reconnect_s: float = Field(1.0, ge=0.1, le=60)
    """After a bus fault, try to reconnect this often (an unplugged cable) [s]."""

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        """Holds and stops no stiffer than a command may be; a watchdog of two periods."""
        for name in ("hold_kp_nm_per_rad", "stop_kp_nm_per_rad"):
            ordered(self, name, "max_kp_nm_per_rad", strict=False)
        for name in ("hold_kd_nms_per_rad", "stop_kd_nms_per_rad"):
            ordered(self, name, "max_kd_nms_per_rad", strict=False)
        ordered(self, "speed_fraction", "overspeed_stop_fraction")
        at_least(self, "command_stale_s", 2 / self.loop_rate_hz,
                 f"two periods of loop_rate_hz={self.loop_rate_hz:g}")  # fmt: skip
        return self


def arm_limits(robot: RobotDescription, q_limits: tuple[np.ndarray, np.ndarray],
               settings: ArmSettings) -> RobotDescription:  # fmt: skip
    """The limits this arm runs under with a person attached: its calibration's joint
    limits ``q_limits`` (inside the URDF's) and fractions of the URDF's speed and effort.
    ConfigurationError: torque limits that could not hold the arm up."""
    holds_its_weight(robot, q_limits, settings.torque_fraction)
    return replace(
        robot,
        q_min=q_limits[0],
        q_max=q_limits[1],
        dq_max=robot.dq_max * settings.speed_fraction,
        tau_max=robot.tau_max * settings.torque_fraction,
    )


def gravity_torques(robot: RobotDescription, q_limits: tuple[np.ndarray, np.ndarray],
                    postures: int = 500, seed: int = 0) -> np.ndarray:  # fmt: skip
    """The largest gravity torque of each joint over ``postures`` seeded postures inside
    ``q_limits`` (the arm alone) [N m], (6,)."""
    import pinocchio as pin

    model = robot.pinocchio_model()
    data = model.createData()
    rng = np.random.default_rng(seed)
    worst = np.zeros(model.nv)
    for q in rng.uniform(q_limits[0], q_limits[1], size=(postures, model.nq)):
        worst = np.maximum(worst, np.abs(pin.computeGeneralizedGravity(model, data, q)))
    return worst


def holds_its_weight(robot: RobotDescription, q_limits: tuple[np.ndarray, np.ndarray],
                     torque_fraction: float) -> None:  # fmt: skip
    """ConfigurationError (one line, the variable, its range, the value) unless the torque
    limits hold the arm's own weight ``WEIGHT_MARGIN`` times over in every posture: a
    smaller limit lets a joint fall at torque-on while the service reports a hold."""
    needed = np.ceil(100 * WEIGHT_MARGIN * gravity_torques(robot, q_limits) / robot.tau_max) / 100
    joint = int(np.argmax(needed))
    if needed[joint] > torque_fraction:
        name = robot.joint_names[joint]
        raise ConfigurationError(
            f"invalid setting: DAMMRL_ARM_TORQUE_FRACTION={torque_fraction:g}: outside its "
            f"range [{needed[joint]:.2f}, 1] for this arm ({name} needs {needed[joint]:.2f} "
            f"of its {robot.tau_max[joint]:g} N m to hold the arm's own weight "
            f"{WEIGHT_MARGIN:g} times)"
        )
