"""The URDF is one source for MuJoCo, pinocchio and ikpy: the three agree."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from dammrl_core.dynamics import ArmModel
from dammrl_core.errors import RobotDescriptionError
from dammrl_core.robot import RobotDescription
from dammrl_core.sim.simulation import Simulation
from tests.conftest import random_postures


def test_reference_arm_has_realistic_limits(robot: RobotDescription) -> None:
    assert len(robot.joint_names) == 6
    assert np.all(robot.q_min < robot.q_max)
    assert np.all((robot.tau_max >= 10) & (robot.tau_max <= 100))
    assert np.all((robot.dq_max >= 1) & (robot.dq_max <= 3))


def test_reach_of_the_arm_is_between_60_and_80_cm(arm: ArmModel) -> None:
    straight = np.zeros(6)
    reach = np.linalg.norm(arm.ee_position(straight))
    assert 0.6 <= reach <= 0.8


def test_pinocchio_fk_agrees_with_mujoco_site(
    sim: Simulation, arm: ArmModel, robot: RobotDescription
) -> None:
    for q in random_postures(robot, 20, seed=1):
        sim.data.qpos[:6] = q
        mujoco.mj_forward(sim.model, sim.data)
        np.testing.assert_allclose(arm.ee_position(q), sim.data.site("ee").xpos, atol=1e-9)


def test_ikpy_fk_agrees_with_pinocchio(arm: ArmModel, robot: RobotDescription) -> None:
    chain = robot.ikpy_chain()
    for q in random_postures(robot, 10, seed=2):
        full = np.zeros(len(chain.links))
        full[np.asarray(chain.active_links_mask)] = q
        np.testing.assert_allclose(
            chain.forward_kinematics(full)[:3, 3], arm.ee_position(q), atol=1e-9
        )


def test_mujoco_and_pinocchio_masses_agree(sim: Simulation, arm: ArmModel) -> None:
    arm_bodies = slice(1, sim.model.body("button").id)
    assert sim.model.body_mass[arm_bodies].sum() == pytest.approx(
        sum(inertia.mass for inertia in arm.model.inertias[1:]) + 4.0  # + the fixed base link
    )


def test_missing_urdf_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(RobotDescriptionError, match="does not exist"):
        RobotDescription.from_urdf(tmp_path / "nope.urdf")


def test_unknown_end_effector_frame_is_a_clear_error() -> None:
    with pytest.raises(RobotDescriptionError, match="no frame 'hand_tip'"):
        RobotDescription.from_urdf(ee_frame="hand_tip")


def test_urdf_with_wrong_joint_count_is_refused(tmp_path: Path) -> None:
    urdf = tmp_path / "two_links.urdf"
    urdf.write_text(
        """<robot name="r"><link name="a"/><link name="b"/>
        <joint name="j" type="revolute"><parent link="a"/><child link="b"/>
        <limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>"""
    )
    with pytest.raises(RobotDescriptionError, match="expected 6"):
        RobotDescription.from_urdf(urdf, ee_frame="b")


def test_another_urdf_with_other_names_runs_a_reach(tmp_path: Path) -> None:
    """Nothing depends on the reference arm's names: rename every joint and the tool."""
    from dammrl.stack.runner import ReachRunner, ReachSettings
    from dammrl_core.robot import DEFAULT_URDF, RobotSettings

    text = DEFAULT_URDF.read_text()
    for name in RobotDescription.from_urdf().joint_names:
        text = text.replace(f'name="{name}"', f'name="r_{name}"')
    text = text.replace('"fingertip"', '"tool0"')
    urdf = tmp_path / "renamed.urdf"
    urdf.write_text(text)
    runner = ReachRunner(ReachSettings(robot=RobotSettings(urdf_path=urdf, ee_frame="tool0")))
    assert runner.robot.joint_names[0] == "r_shoulder_yaw"
    assert runner.run(seed=1, model=(2, 1)).metrics.success
