"""Both IK solvers reach reachable targets and never jump."""

from __future__ import annotations

import numpy as np
import pytest

from dammrl_core.dynamics import ArmModel
from dammrl_core.ik import DampedLeastSquaresIK, IKLatency, IkpyIK
from dammrl_core.robot import RobotDescription
from tests.conftest import HOME_Q, random_postures


@pytest.fixture(scope="module")
def solvers(arm: ArmModel) -> list[DampedLeastSquaresIK | IkpyIK]:
    return [DampedLeastSquaresIK(arm), IkpyIK(arm)]


def test_both_solvers_reach_random_reachable_targets(
    solvers: list[DampedLeastSquaresIK | IkpyIK], arm: ArmModel, robot: RobotDescription
) -> None:
    for q_true in random_postures(robot, 15, seed=5):
        target = arm.ee_position(q_true)
        for solver in solvers:
            result = solver.solve(target, HOME_Q)
            assert result.error_m <= 1e-4, solver.name
            np.testing.assert_allclose(arm.ee_position(result.q), target, atol=1e-4)
            assert robot.within_limits(result.q)


def test_solutions_stay_inside_the_step_bound(arm: ArmModel) -> None:
    target = arm.ee_position(HOME_Q) + np.array([0.2, 0.1, 0.1])  # far: needs > 0.1 rad moves
    for solver in (DampedLeastSquaresIK(arm, max_step_rad=0.1), IkpyIK(arm, max_step_rad=0.1)):
        result = solver.solve(target, HOME_Q)
        assert np.max(np.abs(result.q - HOME_Q)) <= 0.1 + 1e-9
        assert result.error_m > 1e-3  # the bound, not the target, decided


def test_unreachable_target_reports_its_error(arm: ArmModel) -> None:
    result = DampedLeastSquaresIK(arm).solve(np.array([1.5, 0.0, 0.0]), HOME_Q)
    assert result.error_m > 0.5


def test_model_latency_is_seeded_and_lognormal() -> None:
    draw = IKLatency("model", "ikpy", np.random.default_rng(0), median_s=0.02, sigma=0.5)
    again = IKLatency("model", "ikpy", np.random.default_rng(0), median_s=0.02, sigma=0.5)
    samples = np.array([draw(0.0) for _ in range(4000)])
    assert [again(0.0) for _ in range(5)] == samples[:5].tolist()
    assert np.median(samples) == pytest.approx(0.02, rel=0.05)
    assert np.std(np.log(samples)) == pytest.approx(0.5, rel=0.05)


def test_measured_latency_is_the_solve_time() -> None:
    assert IKLatency("measured", "pinocchio", np.random.default_rng(0))(0.123) == 0.123
    assert IKLatency("zero", "pinocchio", np.random.default_rng(0))(0.123) == 0.0


def test_every_latency_spent_is_kept_and_a_replay_hands_them_out_again() -> None:
    measured = IKLatency("measured", "ikpy", np.random.default_rng(0))
    spent = [measured(t) for t in (0.031, 0.052, 0.044)]
    assert measured.spent_s == spent == [0.031, 0.052, 0.044]
    replay = IKLatency("measured", "ikpy", np.random.default_rng(0), replay=measured.spent_s)
    assert [replay(9.9) for _ in range(3)] == spent  # the solve's own time is not used
    assert replay.spent_s == spent


def test_a_replay_that_runs_out_or_holds_a_bad_latency_fails_in_words() -> None:
    from dammrl_core.errors import ConfigurationError

    short = IKLatency("measured", "ikpy", np.random.default_rng(0), replay=[0.01])
    short(0.0)
    with pytest.raises(ConfigurationError, match="ran out at solve 2"):
        short(0.0)
    for bad in (-0.1, float("nan"), 120.0):
        with pytest.raises(ConfigurationError, match="must be 0-60 s"):
            IKLatency("measured", "ikpy", np.random.default_rng(0), replay=[bad])


def test_solves_report_their_processor_time_beside_their_wall_time(arm: ArmModel) -> None:
    target = arm.ee_position(HOME_Q) + np.array([0.01, 0.0, 0.0])
    for solver in (DampedLeastSquaresIK(arm), IkpyIK(arm)):
        result = solver.solve(target, HOME_Q)
        assert 0.0 < result.cpu_s <= result.compute_s + 1e-3, solver.name


def test_solves_count_their_work_in_forward_kinematics_evaluations(arm: ArmModel) -> None:
    """ikpy's optimiser evaluates the chain once per forward-kinematics call (counted on
    the chain it is given), damped least squares once per iteration; the same solve is the
    same work, whatever the clock."""
    near = arm.ee_position(HOME_Q) + np.array([0.005, 0.0, 0.0])
    far = arm.ee_position(HOME_Q) + np.array([0.05, 0.03, 0.0])
    ikpy, dls = IkpyIK(arm), DampedLeastSquaresIK(arm)
    assert ikpy.solve(near, HOME_Q).evaluations > 6  # at least a gradient's worth
    assert ikpy.solve(far, HOME_Q).evaluations == ikpy.solve(far, HOME_Q).evaluations
    assert 0 < dls.solve(near, HOME_Q).evaluations <= dls.max_iterations


def test_reference_latency_is_the_work_at_the_reference_cost_whatever_the_clock() -> None:
    """'reference': evaluations x the reference machine's cost per evaluation x its
    lognormal spread drawn from the seed, so this computer's speed never enters; scaled
    by ``scale``; a measured latency is scaled too, a replay is not."""
    from dammrl_core.ik import REFERENCE_COST

    cost = REFERENCE_COST["ikpy"]
    first = IKLatency("reference", "ikpy", np.random.default_rng(7))
    again = IKLatency("reference", "ikpy", np.random.default_rng(7), scale=2.0)
    times = [first(measured, 300) for measured in (0.001, 5.0, 0.2)]  # the clock is ignored
    assert [again(0.0, 300) for _ in range(3)] == pytest.approx([2 * t for t in times])
    z = np.random.default_rng(7).standard_normal(3)
    assert times == pytest.approx(list(300 * cost.per_evaluation_s * np.exp(cost.sigma * z)))
    assert first.evaluations == [300, 300, 300]
    assert IKLatency("measured", "ikpy", np.random.default_rng(0), scale=3.0)(0.01) == 0.03
    replay = IKLatency("reference", "ikpy", np.random.default_rng(0), replay=[0.02], scale=5.0)
    assert replay(1.0, 10) == 0.02


@pytest.mark.parametrize("scale", [0.0, -1.0, 101.0, float("nan")])
def test_a_latency_scale_outside_its_range_is_refused_in_one_line(scale: float) -> None:
    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match="ik_latency_scale must be in"):
        IKLatency("model", "ikpy", np.random.default_rng(0), scale=scale)
    with pytest.raises(ValueError, match=r"(?i)ik_latency_scale"):
        ControllerSettings(ik_latency_scale=scale)
