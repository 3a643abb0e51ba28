"""What the page draws of the arm and the task, in world coordinates [m]: the URDF's
collision shapes (cylinders, boxes, spheres) posed by pinocchio's forward kinematics, the
table, the goal button, the subgoal and its admission sphere; the page projects them
through a fixed camera (``CAMERA``) onto a 2D canvas (no WebGL: a screen without a GPU
draws it at once, and the first view is never black).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dammrl_core.robot import RobotDescription
from dammrl_core.task import TaskSettings

CAMERA = {"eye": (0.32, -1.1, 0.40), "look_at": (0.32, 0.0, -0.14)}
"""Where a seated participant beside the arm looks from: from the side, above the table,
so that forward (+x, the primary axis) goes to the right of the screen as the forward
arrow does."""
SHOWN_M = ((-0.08, -0.2, -0.26), (0.72, 0.2, 0.08))
"""The box the page fits to its canvas [m]: the arm's reach over the table (start and
goal regions, the arm's base)."""
TABLE_SIZE_M = (0.9, 1.0)  # the table top (x, y) the sim's scene stands on
TABLE_CENTRE_XY_M = (0.35, 0.0)
BUTTON_RADIUS_M = 0.03
DIGITS = 4  # 0.1 mm: finer is invisible and costs bytes


@dataclass(frozen=True)
class Shape:
    """One collision shape of a link: its kind, size and placement on its joint."""

    kind: str  # cylinder, box or sphere
    size: tuple[float, ...]  # radius, length | x, y, z | radius [m]
    joint: int
    placement: Any  # pinocchio SE3 of the shape in its joint's frame


class ArmShapes:
    """The URDF's collision shapes and, for a joint vector, what the page draws of them."""

    def __init__(self, robot: RobotDescription) -> None:
        import pinocchio as pin

        self._pin = pin
        self.model = robot.pinocchio_model()
        self.data = self.model.createData()
        geometry = pin.buildGeomFromUrdf(self.model, str(robot.urdf_path), pin.COLLISION)
        self.shapes = [s for s in map(_shape, geometry.geometryObjects) if s is not None]
        self.joints = self.model.nq

    def drawn(self, q: np.ndarray) -> list[list[Any]]:
        """Every shape at ``q`` as the page draws it: ``["c", a, b, radius]`` (a cylinder
        from a to b), ``["b", 8 corners]``, ``["s", centre, radius]``, flat lists [m]."""
        pin = self._pin
        pin.forwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        drawn = []
        for shape in self.shapes:
            world = self.data.oMi[shape.joint] * shape.placement
            position, rotation = np.array(world.translation), np.array(world.rotation)
            drawn.append(_primitive(shape, position, rotation))
        return drawn


def _primitive(shape: Shape, position: np.ndarray, rotation: np.ndarray) -> list[Any]:
    if shape.kind == "cylinder":  # along the shape's own z
        half = rotation[:, 2] * shape.size[1] / 2
        return ["c", *_round(position - half), *_round(position + half), round(shape.size[0], 4)]
    if shape.kind == "box":
        signs = np.array([(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
        corners = position + (signs * np.array(shape.size) / 2) @ rotation.T
        return ["b", *_round(corners.ravel())]
    return ["s", *_round(position), round(shape.size[0], DIGITS)]


def _round(values: np.ndarray) -> list[float]:
    return [round(float(v), DIGITS) for v in values]


def _shape(geometry: Any) -> Shape | None:
    """A collision object as a Shape (None: a kind the page does not draw)."""
    kind = type(geometry.geometry).__name__
    g = geometry.geometry
    if kind == "Cylinder":
        size: tuple[float, ...] = (float(g.radius), 2 * float(g.halfLength))
    elif kind == "Box":
        size = tuple(2 * float(v) for v in g.halfSide)
    elif kind == "Sphere":
        size = (float(g.radius),)
    else:
        return None
    return Shape(kind.lower(), size, int(geometry.parentJoint), geometry.placement)


def stage(task: TaskSettings) -> dict[str, Any]:
    """What never moves: the camera, the table top's corners, the button's size."""
    (cx, cy), (sx, sy), top = TABLE_CENTRE_XY_M, TABLE_SIZE_M, task.table_top_z_m
    corners = [(cx + dx * sx / 2, cy + dy * sy / 2, top)
               for dx, dy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]  # fmt: skip
    return {
        "camera": CAMERA,
        "shown": SHOWN_M,
        "table": corners,
        "button_radius_m": BUTTON_RADIUS_M,
    }
