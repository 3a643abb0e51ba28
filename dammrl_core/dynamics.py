"""Rigid-body model of the arm for the controller (pinocchio): FK, Jacobian, dynamics."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from dammrl_core.robot import RobotDescription

_WORLD_ALIGNED = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


class ArmModel:
    """Kinematics and inverse dynamics of the end-effector point of a 6-DoF arm.

    The dynamics are those MuJoCo simulates: rigid bodies and armature (pinocchio's RNEA
    includes ``model.armature``) plus viscous joint damping, which RNEA leaves out.
    """

    def __init__(self, robot: RobotDescription) -> None:
        self.robot = robot
        self.model = robot.pinocchio_model()
        self.data = self.model.createData()
        self.ee_frame_id = self.model.getFrameId(robot.ee_frame)

    def ee_position(self, q: np.ndarray) -> np.ndarray:
        """End-effector position [m] (3,) at joint positions ``q`` [rad] (6,)."""
        pin.forwardKinematics(self.model, self.data, q)
        return np.array(
            pin.updateFramePlacement(self.model, self.data, self.ee_frame_id).translation
        )

    def ee_position_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """End-effector position (3,) and linear Jacobian (3, 6) in one kinematics pass."""
        J = pin.computeFrameJacobian(self.model, self.data, q, self.ee_frame_id, _WORLD_ALIGNED)
        placement = pin.updateFramePlacement(self.model, self.data, self.ee_frame_id)
        return np.array(placement.translation), np.array(J[:3])

    def ee_jacobian(self, q: np.ndarray) -> np.ndarray:
        """Linear Jacobian of the end-effector point (3, 6), world-aligned axes."""
        J = pin.computeFrameJacobian(self.model, self.data, q, self.ee_frame_id, _WORLD_ALIGNED)
        return np.array(J[:3])

    def inverse_dynamics(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """tau = M(q) ddq + C(q, dq) dq + g(q) + D dq [N m] (6,)."""
        tau = pin.rnea(self.model, self.data, q, dq, ddq)
        return np.asarray(tau + self.robot.damping * dq)

    def inverse_dynamics_many(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """``inverse_dynamics`` row by row of (n, 6) arrays (the same numbers bit for bit:
        the damping term is the same elementwise product and sum, done once for all rows)."""
        rnea, model, data = pin.rnea, self.model, self.data
        tau = np.empty_like(q)
        for k in range(len(q)):
            tau[k] = rnea(model, data, q[k], dq[k], ddq[k])
        return np.asarray(tau + self.robot.damping * dq)

    def ee_drift_acceleration(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Jdot(q, dq) dq: the end-effector acceleration at zero joint acceleration (3,)."""
        pin.forwardKinematics(self.model, self.data, q, dq, np.zeros_like(q))
        pin.updateFramePlacement(self.model, self.data, self.ee_frame_id)
        acc = pin.getFrameClassicalAcceleration(
            self.model, self.data, self.ee_frame_id, _WORLD_ALIGNED
        )
        return np.array(acc.linear)

    def resolved_acceleration(
        self, q: np.ndarray, dq: np.ndarray, ddx_d: np.ndarray, z: np.ndarray
    ) -> np.ndarray:
        """Paper eq.: ddq_d = J# (ddx_d - Jdot dq) + (I - J# J) z (6,).

        ``ddx_d`` is the desired end-effector acceleration [m/s^2] (3,), ``z`` an arbitrary
        joint acceleration [rad/s^2] (6,) that only acts in the null space of J.
        """
        J = self.ee_jacobian(q)
        J_pinv = np.linalg.pinv(J)
        task = J_pinv @ (ddx_d - self.ee_drift_acceleration(q, dq))
        return np.asarray(task + (np.eye(J.shape[1]) - J_pinv @ J) @ z)


def joint_limit_avoidance(robot: RobotDescription, q: np.ndarray, gain: float) -> np.ndarray:
    """Joint acceleration pushing each joint toward mid-range [rad/s^2] (6,).

    Linear in the normalised distance from mid-range: 0 there, ``gain`` at either limit.
    """
    q_mid = (robot.q_min + robot.q_max) / 2
    half_span = (robot.q_max - robot.q_min) / 2
    return np.asarray(-gain * (q - q_mid) / half_span)
