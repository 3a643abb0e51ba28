"""The robot description: one URDF, loaded by MuJoCo, pinocchio and ikpy."""

from dammrl_core.robot.description import DEFAULT_URDF, RobotDescription
from dammrl_core.robot.settings import RobotSettings

__all__ = ["DEFAULT_URDF", "RobotDescription", "RobotSettings"]
