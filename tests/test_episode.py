"""Whole reaches in-process: success, determinism, holds without jumps."""

from __future__ import annotations

import numpy as np

from dammrl.stack.runner import ReachRunner, ReachSettings
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.task import ReachTask


def test_event_triggered_reach_presses_the_goal(runner: ReachRunner) -> None:
    result = runner.run(seed=3, model=(2, 1), trigger="event")
    m = result.metrics
    assert m.success and m.outcome == "success" and m.button_pressed
    layout = runner.sim.layout  # success is the press: the fingertip is on the cap
    assert m.final_error_m <= layout.cap_radius_m + layout.fingertip_radius_m
    assert m.n_steps >= 15 and 0.0 <= m.human_error_rate <= 0.5
    assert all(s.trigger == "event" for s in result.steps)


def test_fixed_frequency_reach_steps_on_the_timer_grid(runner: ReachRunner) -> None:
    result = runner.run(seed=3, model=(1, 1), trigger="fixed")
    t0 = result.steps[0].t_s  # the timer starts with the first decision
    decided = np.array([s.t_s for s in result.steps]) - t0
    periods = np.floor(decided / 0.1 + 1e-6)
    assert np.all(np.diff(periods) >= 1)  # at most one step per timer period
    for previous, step, period in zip(result.steps, result.steps[1:], periods[1:], strict=False):
        tick = t0 + period * 0.1
        if step.t_s - tick >= runner.control_dt_s / 2:  # a late step: the previous solve
            assert previous.start_s > tick  # was still running when the timer ticked


def test_same_seed_same_reach(runner: ReachRunner) -> None:
    a, b = runner.run(seed=5, model=(1, 2)), runner.run(seed=5, model=(1, 2))
    assert a.summary() == b.summary()
    np.testing.assert_array_equal(a.trajectory.x, b.trajectory.x)


def test_unreachable_goal_ends_in_a_hold_with_a_reason_and_no_jump(runner: ReachRunner) -> None:
    task = runner.sample(0)
    far = ReachTask(task.start, np.array([0.95, 0.0, -0.05]))  # beyond the 0.74 m reach
    result = runner.run(seed=0, model=(2, 8), task=far)
    m = result.metrics
    assert not m.success and m.outcome == "hold"
    assert "workspace" in m.reason or "IK" in m.reason
    q = result.trajectory.q
    dt = runner.control_dt_s
    assert np.max(np.abs(np.diff(q, axis=0))) / dt < runner.robot.dq_max.max()
    after_hold = result.trajectory.t >= m.t_total_s + 0.3
    assert np.max(np.linalg.norm(result.trajectory.v[after_hold], axis=1)) < 0.01  # at rest


def test_reach_with_resolved_acceleration_feedforward_succeeds() -> None:
    runner = ReachRunner(
        ReachSettings(controller=ControllerSettings(feedforward="resolved_acceleration"))
    )
    assert runner.run(seed=2, model=(2, 1)).metrics.success


def test_reach_with_ikpy_succeeds() -> None:
    runner = ReachRunner(ReachSettings(controller=ControllerSettings(ik_solver="ikpy")))
    result = runner.run(seed=1, model=(1, 8))
    assert result.metrics.outcome in ("success", "timeout")
    assert all(s.ik_compute_s > 0 for s in result.steps)


def test_a_reach_with_measured_ik_latency_replays_byte_for_byte() -> None:
    """ikpy in the loop, each solve's own processor time in simulated time: a rerun would
    differ, a replay of the latencies it spent does not."""
    settings = ControllerSettings(ik_solver="ikpy", ik_latency="measured", trigger="fixed")
    runner = ReachRunner(ReachSettings(controller=settings))
    measured = runner.run(seed=3, model=(2, 1))
    spent = measured.ik_latencies_s
    assert len(spent) >= len(measured.steps) > 0 and len(set(spent)) > 1
    assert [s.ik_latency_s for s in measured.steps] == spent[: len(measured.steps)]
    replayed = runner.run(seed=3, model=(2, 1), ik_latencies=spent)
    assert replayed.summary() == measured.summary() and replayed.ik_latencies_s == spent
    np.testing.assert_array_equal(replayed.trajectory.x, measured.trajectory.x)


def test_fast_forward_reproduces_the_tick_by_tick_loop_exactly(runner: ReachRunner) -> None:
    ticking = ReachRunner(ReachSettings(fast_forward=False))
    for seed, model in ((3, (2, 1)), (4, (1, 6))):
        fast, slow = runner.run(seed, model), ticking.run(seed, model)
        assert fast.summary() == slow.summary()
        np.testing.assert_array_equal(fast.trajectory.x, slow.trajectory.x)
        np.testing.assert_array_equal(fast.trajectory.t, slow.trajectory.t)


def test_fast_forward_keeps_the_hold_observation(runner: ReachRunner) -> None:
    task = runner.sample(0)
    far = ReachTask(task.start, np.array([0.95, 0.0, -0.05]))
    ticking = ReachRunner(ReachSettings(fast_forward=False))
    fast, slow = runner.run(0, (2, 8), task=far), ticking.run(0, (2, 8), task=far)
    assert fast.summary() == slow.summary()
    np.testing.assert_array_equal(fast.trajectory.q, slow.trajectory.q)


def test_a_miscalibrated_arm_still_enters_small_admission_spheres() -> None:
    """Link lengths and encoder zeros off by a few percent / milliradians (randomisation):
    the controller's nominal IK alone lands every step millimetres beside its subgoal,
    outside a 4 mm sphere; aimed at subgoal minus the measured calibration offset it lands
    inside, and the reach is the same one the nominal arm makes."""
    from dammrl_core.sim.settings import DomainRandomization, SimSettings

    randomised = SimSettings(randomization=DomainRandomization(enabled=True))
    outcomes = {}
    for correction in (True, False):
        controller = ControllerSettings(calibration_correction=correction)
        runner = ReachRunner(ReachSettings(sim=randomised, controller=controller))
        outcomes[correction] = [runner.run(seed, model=(2, 1)).metrics for seed in range(6)]
    assert all(m.success for m in outcomes[True])
    missed = [m for m in outcomes[False] if not m.success]
    assert len(missed) >= 3 and all("no trigger" in m.reason for m in missed)
