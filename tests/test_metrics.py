"""Metrics against hand-computed and analytic values."""

from __future__ import annotations

import numpy as np
import pytest

from dammrl_core.metrics import (
    Dwell,
    _turning_points,
    decisions_until_stable,
    human_error_rate,
    integrated_squared_jerk,
    log_dimensionless_jerk,
    n_oscillations,
    reach_metrics,
    spectral_arc_length,
)


def _min_jerk(
    distance: float, duration: float, rate_hz: float = 2000.0
) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, duration + 0.5 / rate_hz, 1.0 / rate_hz)
    s = t / duration
    speed = distance / duration * (30 * s**2 - 60 * s**3 + 30 * s**4)
    return t, np.stack([speed, 0 * speed, 0 * speed], axis=1)


def test_isj_of_a_minimum_jerk_reach_matches_the_analytic_value() -> None:
    t, v = _min_jerk(0.3, 1.5)
    assert integrated_squared_jerk(t, v) == pytest.approx(720 * 0.3**2 / 1.5**5, rel=0.01)


GAUSSIAN_T = np.arange(-1.0, 1.0, 0.01)  # the published reference: 100 Hz, t in [-1, 1)
GAUSSIAN = np.exp(-5 * GAUSSIAN_T**2)


def test_sparc_and_ldlj_match_the_published_reference_values() -> None:
    """Balasubramanian et al. 2015: SPARC -1.41403, LDLJ -5.81636."""
    assert spectral_arc_length(GAUSSIAN, 100.0) == pytest.approx(-1.41403, abs=5e-6)
    assert log_dimensionless_jerk(GAUSSIAN, 100.0) == pytest.approx(-5.81636, abs=5e-6)


def test_sparc_and_ldlj_ignore_amplitude_and_duration() -> None:
    for measure in (spectral_arc_length, log_dimensionless_jerk):
        base = measure(GAUSSIAN, 100.0)
        assert measure(3.0 * GAUSSIAN, 100.0) == pytest.approx(base, abs=1e-9)
        slow = np.exp(-5 * np.arange(-1.0, 1.0, 0.005) ** 2)  # the same shape, twice as long
        assert measure(slow, 100.0) == pytest.approx(base, abs=0.01)


def test_stop_and_go_is_less_smooth_than_one_reach() -> None:
    two = np.concatenate([GAUSSIAN, GAUSSIAN])
    assert spectral_arc_length(two, 100.0) < spectral_arc_length(GAUSSIAN, 100.0)
    assert log_dimensionless_jerk(two, 100.0) < log_dimensionless_jerk(GAUSSIAN, 100.0)


SUBGOAL = np.zeros((1, 3))
RATE_HZ = 1000.0  # the synthetic paths below: 1000 samples over 1 s
RADIUS = np.array([0.004])


def test_oscillation_count_ignores_noise_within_the_deadband() -> None:
    rng = np.random.default_rng(0)
    x = np.zeros((500, 3)) + rng.normal(0, 2e-4, (500, 3))
    assert n_oscillations(x, SUBGOAL, RADIUS, RATE_HZ, deadband_m=0.001) == 0


def test_oscillation_count_counts_reversals_near_a_subgoal_per_axis() -> None:
    t = np.linspace(0, 1, 1000)
    x = np.zeros((1000, 3))
    x[:, 0] = 0.003 * np.sin(2 * np.pi * 3 * t)  # 3 periods: 6 extrema, each reversed
    x[:, 2] = 0.003 * np.sin(2 * np.pi * 1 * t)  # 1 period: 2 turning points
    assert n_oscillations(x, SUBGOAL, RADIUS, RATE_HZ, deadband_m=0.001) == 6 + 2


def test_oscillations_are_counted_on_motion_not_on_sensor_noise() -> None:
    """A long wait at a subgoal with the sim's end-effector noise (0.25 mm) turns the raw
    path many times past a 1 mm deadband; the motion estimate does not. Chatter at the
    fixed-frequency timer's 5 Hz survives the filter."""
    rate, n = 100.0, 3000  # 30 s at the control rate
    rng = np.random.default_rng(1)
    noise = rng.normal(0, 2.5e-4, (n, 3))
    raw = [i for axis in range(3) for i in _turning_points(noise[:, axis], 0.001)]
    assert len(raw) > 5
    assert n_oscillations(noise, SUBGOAL, RADIUS, rate) == 0
    t = np.arange(n) / rate
    chatter = noise.copy()
    chatter[:100, 0] += 0.002 * np.sin(2 * np.pi * 5 * t[:100])  # 1 s of 5 Hz chatter
    assert n_oscillations(chatter, SUBGOAL, RADIUS, rate) >= 8


def test_reversals_far_from_every_subgoal_do_not_count() -> None:
    t = np.linspace(0, 1, 1000)
    x = np.zeros((1000, 3))
    x[:, 0] = 0.003 * np.sin(2 * np.pi * 3 * t)
    far = np.array([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    assert n_oscillations(x, far, np.array([0.004, 0.004]), RATE_HZ) == 0
    assert n_oscillations(x, np.zeros((0, 3)), np.zeros(0), RATE_HZ) == 0
    near_second = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert n_oscillations(x, near_second, np.array([0.004, 0.004]), RATE_HZ) == 6


def test_human_error_rate() -> None:
    assert human_error_rate([True, True, False, True]) == 0.25
    assert human_error_rate([]) == 0.0


def test_a_press_needs_a_dwell_not_a_tap() -> None:
    monitor = Dwell(0.1)
    assert not monitor.update(0.0, True)
    assert not monitor.update(0.05, True)
    assert not monitor.update(0.08, False)  # released: the dwell restarts
    assert not monitor.update(0.10, True)
    assert not monitor.done
    assert monitor.update(0.20, True)
    assert not monitor.update(0.21, False) and monitor.done  # once held, it stays done


def test_convergence_counts_the_decisions_before_the_final_choice() -> None:
    assert decisions_until_stable([]) == 0
    assert decisions_until_stable([(2, 1)] * 5) == 0
    assert decisions_until_stable([(1, 8), (1, 8), (2, 1), (2, 1)]) == 2
    assert decisions_until_stable([1, 2, 1, 2, 2]) == 3


def test_an_episode_summary_is_strict_json_even_without_a_step() -> None:
    import json

    from dammrl_core.metrics import episode_summary
    from dammrl_core.task import ReachTask

    metrics = reach_metrics(
        outcome="hold", reason="IK failed", t_end_s=0.5, t=np.arange(0, 0.5, 0.01),
        x=np.zeros((50, 3)), v=np.zeros((50, 3)), goal=np.ones(3), subgoals=np.zeros((0, 3)),
        radii=np.zeros(0), decisions_correct=[], button_pressed=False, reached=False,
    )  # fmt: skip
    task = ReachTask(np.zeros(3), np.ones(3))
    summary = episode_summary(metrics, "event", (2, 1), 7, task)
    assert summary["t_step_mean_s"] is None and summary["n_osc_per_step"] is None
    json.dumps(summary, allow_nan=False)  # raises on NaN or infinity


# ---- the clinical kinematic set, against analytic profiles --------------------------


def _min_jerk_path(
    distance: float, duration: float, rate_hz: float = 1000.0, rest_s: float = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A straight minimum-jerk reach along x with ``rest_s`` at rest before and after:
    t (N,), x, v (N, 3)."""
    t = np.arange(0.0, duration + 2 * rest_s, 1.0 / rate_hz)
    s = np.clip((t - rest_s) / duration, 0.0, 1.0)
    position = distance * (10 * s**3 - 15 * s**4 + 6 * s**5)
    speed = distance / duration * (30 * s**2 - 60 * s**3 + 30 * s**4)
    zeros = 0 * t
    return t, np.stack([position, zeros, zeros], 1), np.stack([speed, zeros, zeros], 1)


def test_a_minimum_jerk_reach_has_its_analytic_kinematics() -> None:
    """Peak speed 1.875 D/T at T/2, one peak, a straight path; the movement time is where
    the speed exceeds 5 % of its peak: 30 s^2 (1-s)^2 = 0.05 * 1.875 at s = 0.0586."""
    from dammrl_core.metrics import kinematics

    t, x, v = _min_jerk_path(0.3, 1.5)
    k = kinematics(t, x, v)
    assert k.peak_speed_m_s == pytest.approx(1.875 * 0.3 / 1.5, rel=1e-3)
    onset = 0.5 * (1 - np.sqrt(1 - 4 * np.sqrt(0.05 * 1.875 / 30)))  # s at 5 % of the peak
    assert k.movement_time_s == pytest.approx(1.5 * (1 - 2 * onset), abs=2e-3)
    assert k.time_to_peak_speed_s == pytest.approx(1.5 * (0.5 - onset), abs=2e-3)
    assert k.n_speed_peaks == 1
    assert k.path_length_ratio == pytest.approx(1.0, abs=1e-3)  # the filter overshoots a hair


def test_two_sub_movements_are_two_speed_peaks_and_a_bump_below_a_tenth_is_none() -> None:
    from dammrl_core.metrics import n_speed_peaks

    t = np.arange(0.0, 2.0, 0.001)
    bump = lambda centre, height: height * np.exp(-(((t - centre) / 0.1) ** 2))  # noqa: E731
    assert n_speed_peaks(bump(0.5, 1.0) + bump(1.2, 0.6)) == 2
    assert n_speed_peaks(bump(0.5, 1.0) + bump(1.2, 0.05)) == 1  # 5 % of the peak
    assert n_speed_peaks(np.zeros_like(t)) == 0


def test_a_semicircle_has_a_path_length_ratio_of_half_pi() -> None:
    from dammrl_core.metrics import path_length_ratio

    angle = np.linspace(0.0, np.pi, 2001)
    semicircle = np.stack([0.1 * np.cos(angle), 0.1 * np.sin(angle), 0 * angle], 1)
    assert path_length_ratio(semicircle) == pytest.approx(np.pi / 2, rel=1e-6)
    assert path_length_ratio(np.zeros((5, 3))) == 1.0  # no displacement: no detour


def test_an_l_shaped_reach_has_its_path_length_ratio_and_sensor_noise_adds_no_detour() -> None:
    """Two minimum-jerk legs at right angles (0.2 m then 0.2 m): ratio sqrt(2); the same
    with 0.5 mm of white position noise stays within 2 % (the motion estimate)."""
    from dammrl_core.metrics import kinematics

    t, leg, speed = _min_jerk_path(0.2, 1.0, rest_s=0.2)
    x = np.concatenate([leg, leg[-1] + leg[:, [1, 0, 2]]])
    v = np.concatenate([speed, speed[:, [1, 0, 2]]])
    t = np.arange(len(x)) * 0.001
    assert kinematics(t, x, v).path_length_ratio == pytest.approx(np.sqrt(2), rel=1e-3)
    noisy = x + np.random.default_rng(0).normal(0.0, 0.0005, x.shape)
    k = kinematics(t, noisy, v)
    assert k.path_length_ratio == pytest.approx(np.sqrt(2), rel=0.02)
    assert k.n_speed_peaks == 2
