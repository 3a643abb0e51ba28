"""Which arm: one settings class read by every service that needs the robot description."""

from __future__ import annotations

from pathlib import Path

from pydantic_settings import SettingsConfigDict

from dammrl_core.robot.description import DEFAULT_URDF, RobotDescription
from dammrl_core.settings import PerJointArmature, Settings


class RobotSettings(Settings):
    """The arm's description, environment prefix ``DAMMRL_ROBOT_``."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_ROBOT_")

    urdf_path: Path = DEFAULT_URDF
    """Any 6-DoF URDF; the default is the dammrl reference rehabilitation arm."""
    ee_frame: str = "fingertip"
    """URDF link whose origin is the end-effector point x."""
    armature_kgm2: PerJointArmature = (0.05, 0.05, 0.03, 0.03, 0.01, 0.01)
    """Reflected rotor inertia per joint [kg m^2] (no URDF tag exists for it)."""

    def load(self) -> RobotDescription:
        """The robot description these settings name."""
        return RobotDescription.from_urdf(self.urdf_path, self.ee_frame, self.armature_kgm2)
