"""The simulation applies the joint impedance law inside MuJoCo, saturated and latched."""

from __future__ import annotations

import mujoco
import numpy as np

from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotDescription
from dammrl_core.robot.scene import SceneLayout
from dammrl_core.sim.settings import DomainRandomization, SimSettings
from dammrl_core.sim.simulation import Simulation
from dammrl_core.state import JointCommand
from tests.conftest import HOME_Q, random_postures


def _command(
    q_ref: np.ndarray, tau_ff: np.ndarray, kp: float = 300.0, kd: float = 20.0
) -> JointCommand:
    return JointCommand(q_ref, np.zeros(6), tau_ff, np.full(6, kp), np.full(6, kd))


def test_feedforward_equals_mujoco_inverse_dynamics(sim: Simulation, arm: ArmModel) -> None:
    rng = np.random.default_rng(0)
    m, d = sim.model, sim.data
    for q in random_postures(sim.robot, 20, seed=3, spread=1.0):
        dq, ddq = rng.normal(0, 1.0, 6), rng.normal(0, 3.0, 6)
        d.qpos[:6], d.qvel[:6], d.qacc[:6] = q, dq, ddq
        d.qpos[6] = d.qvel[6] = d.qacc[6] = 0.0
        mujoco.mj_inverse(m, d)
        assert d.ncon == 0
        np.testing.assert_allclose(arm.inverse_dynamics(q, dq, ddq), d.qfrc_inverse[:6], atol=1e-9)


def test_command_law_is_feedforward_plus_pd(sim: Simulation) -> None:
    state = sim.reset(HOME_Q, (0.5, 0.0))
    q_ref, tau_ff = HOME_Q + 0.01, np.array([1.0, -2.0, 0.5, 0.3, 0.1, -0.1])
    sim.apply(_command(q_ref, tau_ff, kp=100.0, kd=5.0))
    sim.step(1)
    expected = tau_ff + 100.0 * (q_ref - state.q) + 5.0 * (0.0 - state.dq)
    np.testing.assert_allclose(sim.read().tau, expected, rtol=1e-9)


def test_command_beyond_effort_limits_is_saturated(sim: Simulation) -> None:
    sim.reset(HOME_Q, (0.5, 0.0))
    huge = np.array([500.0, -500.0, 500.0, -500.0, 500.0, -500.0])
    sim.apply(_command(HOME_Q, huge))
    sim.step(1)
    tau_max = sim.robot.tau_max
    np.testing.assert_allclose(sim.read().tau, np.sign(huge) * tau_max)
    assert np.all(np.abs(sim.data.qfrc_actuator[:6]) <= tau_max + 1e-9)


def test_gravity_feedforward_holds_the_arm_still(sim: Simulation, arm: ArmModel) -> None:
    sim.reset(HOME_Q, (0.5, 0.0))
    sim.apply(_command(HOME_Q, arm.inverse_dynamics(HOME_Q, np.zeros(6), np.zeros(6)), kp=0, kd=0))
    sim.step(1000)
    np.testing.assert_allclose(sim.read().q, HOME_Q, atol=1e-6)


def test_command_is_held_between_commands(sim: Simulation, arm: ArmModel) -> None:
    sim.reset(HOME_Q, (0.5, 0.0))
    target = HOME_Q + np.array([0.1, -0.1, 0.1, 0.1, 0.1, 0.1])
    tau = arm.inverse_dynamics(target, np.zeros(6), np.zeros(6))
    sim.apply(_command(target, tau))
    sim.step(3000)
    np.testing.assert_allclose(sim.read().q, target, atol=2e-3)


def test_button_registers_a_press_when_pushed(sim: Simulation) -> None:
    sim.reset(HOME_Q, (0.5, 0.0))
    sim.data.qpos[6] = -0.005
    mujoco.mj_forward(sim.model, sim.data)
    assert sim.read().button_pressed
    sim.data.qpos[6] = -0.001
    mujoco.mj_forward(sim.model, sim.data)
    assert not sim.read().button_pressed


def test_button_spring_returns_the_cap(sim: Simulation) -> None:
    sim.reset(HOME_Q, (0.5, 0.0))
    sim.data.qpos[6] = -0.01
    sim.step(500)
    assert abs(sim.data.qpos[6]) < 1e-3


def _sim(settings: SimSettings, seed: int | None = None) -> Simulation:
    return Simulation(settings, RobotDescription.from_urdf(), SceneLayout(), seed)


def test_domain_randomization_is_seeded_and_off_by_default() -> None:
    nominal = _sim(SimSettings())
    nominal.reset(HOME_Q, (0.5, 0.0))
    settings = SimSettings(randomization=DomainRandomization(enabled=True))
    a, b = _sim(settings, seed=4), _sim(settings, seed=4)
    a.reset(HOME_Q, (0.5, 0.0))
    b.reset(HOME_Q, (0.5, 0.0))
    np.testing.assert_array_equal(a.model.body_mass, b.model.body_mass)
    assert not np.allclose(a.model.body_mass, nominal.model.body_mass)
    assert np.all(a.model.dof_frictionloss[:6] > 0)
    assert np.all(nominal.model.dof_frictionloss == 0)
    assert not np.array_equal(a.read().q, HOME_Q)  # sensor noise


def test_the_end_effector_velocity_is_as_noisy_as_its_setting_says() -> None:
    """At rest the true velocity is zero: what the sensor reads is the noise alone, with
    the set standard deviation on every axis (the event trigger's dV/dt reads it)."""
    quiet = DomainRandomization(enabled=True, ee_vel_noise_m_per_s=0.0)
    noisy = DomainRandomization(enabled=True, ee_vel_noise_m_per_s=1e-3)
    readings = {}
    for name, randomization in (("quiet", quiet), ("noisy", noisy)):
        sim = _sim(SimSettings(randomization=randomization), seed=2)
        sim.reset(HOME_Q, (0.5, 0.0))
        readings[name] = np.array([sim.read().ee_vel for _ in range(4000)])
    true_velocity = readings["quiet"].mean(axis=0)
    np.testing.assert_allclose(readings["quiet"], np.tile(true_velocity, (4000, 1)))
    spread = (readings["noisy"] - true_velocity).std(axis=0)
    np.testing.assert_allclose(spread, 1e-3, rtol=0.05)


def test_reset_restores_the_nominal_model() -> None:
    sim = _sim(SimSettings(randomization=DomainRandomization(enabled=True)), seed=1)
    nominal = _sim(SimSettings())
    sim.reset(HOME_Q, (0.5, 0.0))
    sim.settings = SimSettings()
    sim.reset(HOME_Q, (0.5, 0.0))
    np.testing.assert_array_equal(sim.model.body_mass, nominal.model.body_mass)
    np.testing.assert_array_equal(sim.model.body_pos[:9], nominal.model.body_pos[:9])
    np.testing.assert_array_equal(sim.joint_offset, np.zeros(6))


def test_a_reset_reads_the_same_state_whatever_ran_before() -> None:
    """A command latches its gains into the model; a reset restores them, so the state a
    reset reads (its torque included) does not depend on an earlier reach in the process
    (a study's record would otherwise depend on which worker ran it)."""
    used, fresh = _sim(SimSettings()), _sim(SimSettings())
    used.reset(HOME_Q, (0.5, 0.0))
    used.apply(JointCommand(HOME_Q + 0.3, np.zeros(6), np.zeros(6), np.full(6, 50.0),
                            np.full(6, 5.0)))  # fmt: skip
    used.step(10)
    again, first = used.reset(HOME_Q, (0.5, 0.0)), fresh.reset(HOME_Q, (0.5, 0.0))
    np.testing.assert_array_equal(again.tau, first.tau)
    np.testing.assert_array_equal(used.model.actuator_biasprm, fresh.model.actuator_biasprm)


def test_kinematic_randomisation_moves_the_true_arm_not_the_reported_angles() -> None:
    """Link lengths within 2 % and encoder offsets within 5 mrad: the arm reports the
    commanded posture while its fingertip is millimetres from where the nominal model
    (the controller's IK) puts it; the servo holds the reported angle."""
    noise_free = DomainRandomization(enabled=True, q_noise_rad=0, dq_noise_rad_per_s=0,
                                     ee_noise_m=0, ee_vel_noise_m_per_s=0)  # fmt: skip
    sim, nominal = _sim(SimSettings(randomization=noise_free), seed=3), _sim(SimSettings())
    state, reference = sim.reset(HOME_Q, (0.5, 0.0)), nominal.reset(HOME_Q, (0.5, 0.0))
    np.testing.assert_allclose(state.q, HOME_Q, atol=1e-12)  # the encoders read q
    assert np.all(np.abs(sim.joint_offset) <= 0.005) and np.any(sim.joint_offset != 0)
    shift = float(np.linalg.norm(state.ee_pos - reference.ee_pos))
    assert 1e-4 < shift < 0.03, shift
    lengths = sim.model.body_pos[[5, 7, 8], 0] / nominal.model.body_pos[[5, 7, 8], 0]
    assert np.all(np.abs(lengths - 1) <= 0.02) and not np.allclose(lengths, 1)
