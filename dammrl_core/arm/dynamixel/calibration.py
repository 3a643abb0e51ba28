"""One arm's calibration: which servo drives which joint and how (ids, zero offsets,
directions, gear ratios, current-to-torque constants) and joint limits tighter than the
URDF's. Written by ``dammrl robot calibrate``, read through ``DAMMRL_ROBOT_CALIBRATION_FILE``.

Frames: the servo angle is ``direction * gear_ratio * (q + offset)`` for the joint angle
``q`` (both [rad], the servo's angle 0 at the middle of its encoder's turn); the joint
torque is ``direction * gear_ratio * torque_per_amp * current``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dammrl_core.errors import ConfigurationError
from dammrl_core.robot import RobotDescription
from dammrl_core.settings import error_line

TICKS_PER_RAD = 4096 / (2 * math.pi)
CENTRE_TICKS = 2048
Six = Annotated[tuple[float, float, float, float, float, float], Field()]
ServoId = Annotated[int, Field(ge=0, le=252)]


class Calibration(BaseModel):
    """The servos of one arm, base joint first."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    ids: tuple[ServoId, ServoId, ServoId, ServoId, ServoId, ServoId] = (1, 2, 3, 4, 5, 6)
    offsets_rad: Six = (0.0,) * 6
    directions: tuple[Literal[-1, 1], Literal[-1, 1], Literal[-1, 1], Literal[-1, 1],
                      Literal[-1, 1], Literal[-1, 1]] = (1,) * 6  # fmt: skip
    gear_ratios: Six = (1.0,) * 6
    """Servo turns per joint turn (1: the servo is the joint)."""
    torque_per_amp_nm: Six = (20.0, 25.0, 12.0, 12.0, 5.0, 5.0)
    """Servo output torque per ampere [N m/A] (the defaults: the emulated arm's actuators)."""
    q_min_rad: Six | None = None
    """Joint limits for this arm, inside the URDF's (None: the URDF's)."""
    q_max_rad: Six | None = None
    button_id: ServoId | None = 100
    """The goal button's sensor board on the same bus (None: no button)."""

    @model_validator(mode="after")
    def _consistent(self) -> Calibration:
        if len(set(self.ids)) != 6 or (self.button_id is not None and self.button_id in self.ids):
            raise ValueError("servo ids must be six different ids, the button's apart")
        if any(not 0.1 <= g <= 1000 for g in self.gear_ratios):
            raise ValueError("gear ratios must lie in [0.1, 1000]")
        if any(not 0 < k <= 1000 for k in self.torque_per_amp_nm):
            raise ValueError("torque constants must lie in (0, 1000] N m/A")
        if (self.q_min_rad is None) != (self.q_max_rad is None):
            raise ValueError("give both q_min_rad and q_max_rad, or neither")
        return self

    # ---- frames ------------------------------------------------------------------------
    @property
    def _scale(self) -> np.ndarray:
        return np.asarray(np.asarray(self.directions) * np.asarray(self.gear_ratios))

    def servo_rad(self, q_rad: np.ndarray) -> np.ndarray:
        return np.asarray(self._scale * (np.asarray(q_rad) + self.offsets_rad))

    def joint_rad(self, servo_rad: np.ndarray) -> np.ndarray:
        return np.asarray(np.asarray(servo_rad) / self._scale - self.offsets_rad)

    def to_ticks(self, q_rad: np.ndarray) -> list[int]:
        return [round(float(a) * TICKS_PER_RAD) + CENTRE_TICKS for a in self.servo_rad(q_rad)]

    def to_rad(self, ticks: list[int]) -> np.ndarray:
        servo = (np.asarray(ticks, dtype=float) - CENTRE_TICKS) / TICKS_PER_RAD
        return self.joint_rad(servo)

    def joint_velocity(self, servo_rad_s: np.ndarray) -> np.ndarray:
        return np.asarray(np.asarray(servo_rad_s) / self._scale)

    def joint_torque(self, current_a: np.ndarray) -> np.ndarray:
        return np.asarray(self._scale * np.asarray(self.torque_per_amp_nm) * current_a)

    def servo_gain(self, joint_gain: np.ndarray) -> np.ndarray:
        """A joint stiffness or damping [N m/rad, N m s/rad] as the servo's [A/rad, A s/rad]:
        the servo angle is gear times the joint's and the torque gear times the servo's."""
        k = np.asarray(self.gear_ratios) ** 2 * np.asarray(self.torque_per_amp_nm)
        return np.asarray(np.asarray(joint_gain) / k)

    def servo_current(self, joint_torque_nm: np.ndarray) -> np.ndarray:
        """The current limit [A] for a joint torque limit [N m] (magnitudes)."""
        k = np.asarray(self.gear_ratios) * np.asarray(self.torque_per_amp_nm)
        return np.asarray(np.abs(joint_torque_nm) / k)

    # ---- limits ------------------------------------------------------------------------
    def limits(self, robot: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
        """This arm's joint limits: the calibration's, which must lie inside the URDF's."""
        if self.q_min_rad is None or self.q_max_rad is None:
            return robot.q_min.copy(), robot.q_max.copy()
        low, high = np.asarray(self.q_min_rad), np.asarray(self.q_max_rad)
        for i, name in enumerate(robot.joint_names):
            if not robot.q_min[i] <= low[i] < high[i] <= robot.q_max[i]:
                raise ConfigurationError(
                    f"calibration limits of {name} [{low[i]:.3f}, {high[i]:.3f}] rad are not "
                    f"inside the URDF's [{robot.q_min[i]:.3f}, {robot.q_max[i]:.3f}] rad"
                )
        return low, high


def load_calibration(path: Path) -> Calibration:
    """The calibration in ``path``; a clear error naming the file and the field."""
    try:
        return Calibration.model_validate_json(Path(path).read_bytes())
    except OSError as exc:
        raise ConfigurationError(
            f"cannot read the arm calibration {path}: {exc.strerror}"
        ) from None
    except ValidationError as exc:
        raise ConfigurationError(f"arm calibration {path}: {error_line(exc)}") from None


def save_calibration(calibration: Calibration, path: Path) -> None:
    Path(path).write_text(calibration.model_dump_json(indent=2) + "\n")
