"""The MuJoCo scene: the arm from its URDF, a table, and a spring-loaded goal button.

Built with ``MjSpec`` so the URDF stays the single source of the arm. Only the fingertip
and the button cap collide (the task is a press; the workspace box in the controller keeps
the rest of the arm clear of the table). Each arm joint gets one affine actuator whose
force is ``ctrl - kp q - kd dq`` with ``ctrl = tau_ff + kp q_ref + kd dq_ref``: MuJoCo
evaluates the joint impedance law at every physics step, the gains live in
``actuator_biasprm`` and the effort limit is the actuator force range.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco

from dammrl_core.robot.description import RobotDescription

CONTACT_GROUP = 2  # contype/conaffinity bit shared by the fingertip and the button cap


@dataclass(frozen=True)
class SceneLayout:
    """Geometry of the table and button [m]; the task frame is the robot base frame."""

    table_top_z_m: float = -0.25
    table_center_xy_m: tuple[float, float] = (0.45, 0.0)
    table_half_size_xy_m: tuple[float, float] = (0.35, 0.45)
    housing_height_m: float = 0.02
    cap_radius_m: float = 0.03
    cap_height_m: float = 0.01
    button_travel_m: float = 0.02  # mechanical travel of the cap
    button_stiffness_n_per_m: float = 400.0
    button_damping_ns_per_m: float = 5.0
    fingertip_radius_m: float = 0.012
    # the goal pushes the cap this far down: the detection travel (3 mm) plus half the
    # smallest micro-step (10 mm), so a fingertip the controller leaves anywhere inside its
    # deadband around x_g on the vertical axis (half a step, eq. 2) presses the button
    goal_press_depth_m: float = 0.008
    timestep_s: float = 0.001

    @property
    def cap_top_z_m(self) -> float:
        return self.table_top_z_m + self.housing_height_m + self.cap_height_m

    @property
    def goal_z_m(self) -> float:
        """Fingertip-centre height that presses the cap by ``goal_press_depth_m``."""
        return self.cap_top_z_m + self.fingertip_radius_m - self.goal_press_depth_m


def build_scene_spec(robot: RobotDescription, layout: SceneLayout) -> mujoco.MjSpec:
    """Compose arm, table and button into one spec (not yet compiled)."""
    spec = mujoco.MjSpec.from_file(str(robot.urdf_path))
    spec.compiler.fusestatic = False  # keep the end-effector frame as its own body
    spec.option.timestep = layout.timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    _configure_arm(spec, robot, layout)
    _add_table(spec, layout)
    _add_button(spec, layout)
    _add_sensors(spec, robot)
    spec.worldbody.add_light(pos=[0.3, 0.0, 1.5], dir=[0, 0, -1])
    return spec


def build_scene(robot: RobotDescription, layout: SceneLayout) -> mujoco.MjModel:
    """The compiled scene model."""
    return build_scene_spec(robot, layout).compile()


def _configure_arm(spec: mujoco.MjSpec, robot: RobotDescription, layout: SceneLayout) -> None:
    for geom in spec.geoms:
        geom.contype, geom.conaffinity = 0, 0
    ee_body = spec.body(robot.ee_frame)
    for geom in ee_body.geoms:
        geom.contype, geom.conaffinity = CONTACT_GROUP, CONTACT_GROUP
    ee_body.add_site(name="ee", size=[0.004, 0, 0])
    for i, name in enumerate(robot.joint_names):
        spec.joint(name).armature = float(robot.armature[i])
        spec.add_actuator(
            name=name,
            target=name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            gaintype=mujoco.mjtGain.mjGAIN_FIXED,
            gainprm=[1.0] + [0.0] * 9,
            biastype=mujoco.mjtBias.mjBIAS_AFFINE,
            biasprm=[0.0] * 10,
            forcelimited=mujoco.mjtLimited.mjLIMITED_TRUE,
            forcerange=[-float(robot.tau_max[i]), float(robot.tau_max[i])],
        )


def _add_sensors(spec: mujoco.MjSpec, robot: RobotDescription) -> None:
    """One sensordata vector holds the whole robot state (see SENSOR_LAYOUT)."""
    for kind in (mujoco.mjtSensor.mjSENS_JOINTPOS, mujoco.mjtSensor.mjSENS_JOINTVEL):
        for name in robot.joint_names:
            spec.add_sensor(type=kind, objtype=mujoco.mjtObj.mjOBJ_JOINT, objname=name)
    for name in robot.joint_names:
        spec.add_sensor(
            type=mujoco.mjtSensor.mjSENS_ACTUATORFRC,
            objtype=mujoco.mjtObj.mjOBJ_ACTUATOR,
            objname=name,
        )
    for kind in (mujoco.mjtSensor.mjSENS_FRAMEPOS, mujoco.mjtSensor.mjSENS_FRAMELINVEL):
        spec.add_sensor(type=kind, objtype=mujoco.mjtObj.mjOBJ_SITE, objname="ee")
    spec.add_sensor(
        type=mujoco.mjtSensor.mjSENS_JOINTPOS, objtype=mujoco.mjtObj.mjOBJ_JOINT, objname="button"
    )


# slices of MjData.sensordata
SENSOR_LAYOUT = {
    "q": slice(0, 6),
    "dq": slice(6, 12),
    "tau": slice(12, 18),
    "ee_pos": slice(18, 21),
    "ee_vel": slice(21, 24),
    "button": slice(24, 25),
}


def _add_table(spec: mujoco.MjSpec, layout: SceneLayout) -> None:
    half_thickness = 0.02
    cx, cy = layout.table_center_xy_m
    hx, hy = layout.table_half_size_xy_m
    spec.worldbody.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[hx, hy, half_thickness],
        pos=[cx, cy, layout.table_top_z_m - half_thickness],
        rgba=[0.55, 0.45, 0.35, 1.0],
        contype=0,
        conaffinity=0,
    )


def _add_button(spec: mujoco.MjSpec, layout: SceneLayout) -> None:
    base = spec.worldbody.add_body(name="button", pos=[0.45, 0.0, layout.table_top_z_m])
    base.add_geom(
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[layout.cap_radius_m * 1.3, layout.housing_height_m / 2, 0],
        pos=[0, 0, layout.housing_height_m / 2],
        rgba=[0.2, 0.2, 0.2, 1.0],
        contype=0,
        conaffinity=0,
    )
    cap = base.add_body(name="button_cap", pos=[0, 0, layout.housing_height_m])
    cap.add_joint(
        name="button",
        type=mujoco.mjtJoint.mjJNT_SLIDE,
        axis=[0, 0, 1],
        range=[-layout.button_travel_m, 0.0],
        limited=mujoco.mjtLimited.mjLIMITED_TRUE,
        stiffness=layout.button_stiffness_n_per_m,
        damping=layout.button_damping_ns_per_m,
    )
    cap.add_geom(
        name="button_cap",
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[layout.cap_radius_m, layout.cap_height_m / 2, 0],
        pos=[0, 0, layout.cap_height_m / 2],
        mass=0.02,
        rgba=[0.85, 0.1, 0.1, 1.0],
        contype=CONTACT_GROUP,
        conaffinity=CONTACT_GROUP,
    )
