"""The robot description: one URDF, loaded by MuJoCo, pinocchio and ikpy."""

from dammrl.robot.description import DEFAULT_URDF, RobotDescription

__all__ = ["DEFAULT_URDF", "RobotDescription"]
