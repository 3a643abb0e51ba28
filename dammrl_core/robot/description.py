"""Read a 6-DoF arm from its URDF: joint names, limits and the models built from it.

The URDF is the single source of the kinematics and dynamics. pinocchio parses it here
for the controller's model; :mod:`dammrl_core.robot.scene` hands the same file to MuJoCo and
:meth:`RobotDescription.ikpy_chain` to ikpy. Armature (reflected rotor inertia) has no
URDF tag, so it is a setting applied identically to MuJoCo and pinocchio.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from dammrl_core.errors import RobotDescriptionError

if TYPE_CHECKING:
    import ikpy.chain

DEFAULT_URDF = Path(str(resources.files("dammrl_core.robot").joinpath("rehab_arm_6dof.urdf")))
N_JOINTS = 6


@dataclass(frozen=True)
class RobotDescription:
    """Joint limits and names of a 6-DoF serial arm, read from its URDF.

    All arrays have shape (6,), in joint order from base to tip.
    """

    urdf_path: Path
    ee_frame: str
    joint_names: tuple[str, ...]
    q_min: np.ndarray  # [rad]
    q_max: np.ndarray  # [rad]
    dq_max: np.ndarray  # [rad/s]
    tau_max: np.ndarray  # [N m]
    damping: np.ndarray  # [N m s/rad]
    armature: np.ndarray  # [kg m^2]

    @classmethod
    def from_urdf(
        cls,
        urdf_path: Path = DEFAULT_URDF,
        ee_frame: str = "fingertip",
        armature: tuple[float, ...] = (0.05, 0.05, 0.03, 0.03, 0.01, 0.01),
    ) -> RobotDescription:
        """Parse ``urdf_path``; ``ee_frame`` names the end-effector point x."""
        urdf_path = Path(urdf_path)
        if not urdf_path.is_file():
            raise RobotDescriptionError(f"URDF file {urdf_path} does not exist")
        try:
            model = pin.buildModelFromUrdf(str(urdf_path))
        except (RuntimeError, ValueError) as exc:
            raise RobotDescriptionError(f"cannot parse URDF {urdf_path}: {exc}") from exc
        if model.nq != N_JOINTS or model.nv != N_JOINTS:
            raise RobotDescriptionError(
                f"URDF {urdf_path} has {model.nq} joint coordinates, expected {N_JOINTS} "
                "(one revolute or prismatic joint per DoF)"
            )
        if not model.existFrame(ee_frame):
            raise RobotDescriptionError(f"URDF {urdf_path} has no frame {ee_frame!r}")
        if len(armature) != N_JOINTS:
            raise RobotDescriptionError(f"armature needs {N_JOINTS} values, got {len(armature)}")
        return cls(
            urdf_path=urdf_path,
            ee_frame=ee_frame,
            joint_names=tuple(model.names[1:]),
            q_min=np.array(model.lowerPositionLimit, dtype=float),
            q_max=np.array(model.upperPositionLimit, dtype=float),
            dq_max=np.array(model.velocityLimit, dtype=float),
            tau_max=np.array(model.effortLimit, dtype=float),
            damping=np.array(model.damping, dtype=float),
            armature=np.array(armature, dtype=float),
        )

    def pinocchio_model(self) -> pin.Model:
        """The pinocchio model of the arm, with the armature of this description."""
        model = pin.buildModelFromUrdf(str(self.urdf_path))
        model.armature = self.armature.copy()
        return model

    def ikpy_chain(self) -> ikpy.chain.Chain:
        """The ikpy chain from the base link to ``ee_frame``, the six joints active."""
        import ikpy.chain  # imported lazily: ikpy is slow to import and only one solver needs it

        model = pin.buildModelFromUrdf(str(self.urdf_path))
        base = model.frames[1].name  # frame 0 is pinocchio's 'universe', 1 the URDF root link
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # ikpy warns that fixed links default to active
            chain = ikpy.chain.Chain.from_urdf_file(str(self.urdf_path), base_elements=[base])
        names = [link.name for link in chain.links]
        mask = [name in self.joint_names for name in names]
        if sum(mask) != N_JOINTS:
            raise RobotDescriptionError(
                f"ikpy found joints {names} from {base!r}; expected the six joints "
                f"{list(self.joint_names)}"
            )
        chain.active_links_mask = np.array(mask)
        return chain

    def within_limits(self, q: np.ndarray, tolerance_rad: float = 0.0) -> bool:
        """True when every joint lies inside its limits widened by ``tolerance_rad``."""
        return bool(
            np.all(q >= self.q_min - tolerance_rad) and np.all(q <= self.q_max + tolerance_rad)
        )
