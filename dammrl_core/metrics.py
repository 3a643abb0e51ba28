"""Evaluation metrics of a reach: one definition, used by every runner and report.

Conventions: positions in metres, times in seconds, trajectories sampled uniformly at
the control rate (``t`` of shape (N,), positions and velocities of shape (N, 3)).
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.signal import butter, find_peaks, sosfilt, sosfilt_zi  # at import: a service's first

# episode must not pause its loop for SciPy's import (0.5 s: the arm held at the first end)

try:  # SciPy's filter loop (sosfilt's own, in place); tests/test_loop_speed.py pins it
    from scipy.signal._sosfilt import _sosfilt as _sosfilt_rows
except ImportError:  # pragma: no cover - another SciPy: the public wrapper, slower
    _sosfilt_rows = None


@dataclass(frozen=True)
class ReachMetrics:
    """The paper's evaluation metrics for one reach (see each function for definitions)."""

    success: bool  # the button pressed and held for the dwell time (the task done)
    reached: bool  # the paper's criterion: ||x - x_g|| <= eps_g at some time before the end
    outcome: str  # 'success', 'hold', 'timeout', or from outside: 'skipped', 'stopped'
    reason: str  # why the reach ended
    t_total_s: float  # start to goal acquisition (or to the end) [s]
    t_step_mean_s: float  # t_total / n_steps [s]
    final_error_m: float  # ||x - x_g|| at the end [m]
    n_osc: int  # waypoint oscillation count, see n_oscillations
    n_osc_per_step: float  # n_osc / n_steps (NaN without a step)
    jerk_isj: float  # integrated squared jerk [m^2/s^5]
    sparc: float  # spectral arc length of the speed profile [-], see spectral_arc_length
    ldlj: float  # log dimensionless jerk of the speed profile [-], see log_dimensionless_jerk
    human_error_rate: float  # share of human commands pointing away from the goal
    n_steps: int  # micro-steps executed
    n_decisions: int  # human decisions made
    button_pressed: bool  # the goal button was pushed past its detection travel
    # the rehabilitation literature's core kinematic set (see kinematics())
    movement_time_s: float  # movement onset to offset [s]
    peak_speed_m_s: float  # the end-effector's peak speed [m/s]
    time_to_peak_speed_s: float  # movement onset to the peak speed [s]
    n_speed_peaks: int  # local maxima of the speed profile (1: one smooth movement)
    path_length_ratio: float  # path length / straight start-end distance [-] (1: straight)

    def as_dict(self) -> dict[str, Any]:
        """The fields as a JSON-safe dict: a number that is not finite becomes None."""
        return {k: _finite_or_none(v) for k, v in asdict(self).items()}


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def episode_summary(
    metrics: ReachMetrics,
    trigger: str,
    model: tuple[int, int],
    seed: int,
    task: Any,
) -> dict[str, Any]:
    """One finished reach as reported everywhere (``reach --json``, ``up --json``,
    EpisodeResult): the metrics plus what identifies the run. ``task`` has ``start`` and
    ``goal`` (3,) [m]. Valid JSON: no NaN (a reach without a step has no mean step time).
    """
    return {
        **metrics.as_dict(),
        "trigger": trigger,
        "model": [int(model[0]), int(model[1])],
        "seed": int(seed),
        "start_m": np.round(task.start, 4).tolist(),
        "goal_m": np.round(task.goal, 4).tolist(),
    }


def reach_metrics(
    *,
    outcome: str,
    reason: str,
    t_end_s: float,
    t: np.ndarray,
    x: np.ndarray,
    v: np.ndarray,
    goal: np.ndarray,
    subgoals: np.ndarray,
    radii: np.ndarray,
    decisions_correct: list[bool],
    button_pressed: bool,
    reached: bool,
) -> ReachMetrics:
    """All metrics of one reach from its samples up to its end ``t_end_s`` (a success, the
    start of a hold, or the timeout): ``t`` (N,), ``x``, ``v`` (N, 3); the subgoals (M, 3)
    and admission radii (M,) of its M steps; whether each human decision was correct."""
    n_steps = len(subgoals)
    n_osc = n_oscillations(x, subgoals.reshape(-1, 3), radii, _rate(t))
    return ReachMetrics(
        success=outcome == "success",
        reached=reached,
        outcome=outcome,
        reason=reason,
        t_total_s=float(t_end_s),
        t_step_mean_s=float(t_end_s) / n_steps if n_steps else float("nan"),
        final_error_m=float(goal_error(x[-1], goal)[0]),
        n_osc=n_osc,
        n_osc_per_step=n_osc / n_steps if n_steps else float("nan"),
        jerk_isj=integrated_squared_jerk(t, v),
        sparc=spectral_arc_length(_speed(v), _rate(t)),
        ldlj=log_dimensionless_jerk(_speed(v), _rate(t)),
        human_error_rate=human_error_rate(decisions_correct),
        n_steps=n_steps,
        n_decisions=len(decisions_correct),
        button_pressed=button_pressed,
        **asdict(kinematics(t, x, v)),
    )


@dataclass(frozen=True)
class Kinematics:
    """The core kinematic measures of upper-limb reaching used in rehabilitation (the
    measures whose clinimetric properties are best documented: Schwarz et al. 2019,
    Neurorehabil Neural Repair 33:590; smoothness by SPARC and LDLJ beside them)."""

    movement_time_s: float
    peak_speed_m_s: float
    time_to_peak_speed_s: float
    n_speed_peaks: int
    path_length_ratio: float


ONSET_FRACTION = 0.05
"""Movement onset and offset: the speed first rises above and last falls below this share
of its peak (5 %, the usual threshold; Schwarz et al. 2019)."""
PEAK_FRACTION = 0.10
"""A speed peak counts when it stands out of the profile by this share of the peak speed
(its prominence; a dip of less is the same peak). Rohrer et al. 2002 count peaks the same
way on a filtered speed."""


def kinematics(t: np.ndarray, x: np.ndarray, v: np.ndarray) -> Kinematics:
    """Movement time, peak speed, time to peak speed, number of speed peaks and path-length
    ratio of a reach: ``t`` (N,) [s], the measured positions ``x`` and velocities ``v``
    (N, 3). Speed and path are those of :func:`motion_estimate` (sensor noise is neither a
    peak nor a detour). A reach without motion: times 0, no peak, a ratio of 1."""
    if len(t) < 2:
        return Kinematics(0.0, 0.0, 0.0, 0, 1.0)
    speed = _speed(motion_estimate(v, _rate(t)))
    peak = int(np.argmax(speed))
    if speed[peak] <= 0.0:
        return Kinematics(0.0, 0.0, 0.0, 0, 1.0)
    moving = np.nonzero(speed >= ONSET_FRACTION * speed[peak])[0]
    onset, offset = int(moving[0]), int(moving[-1])
    return Kinematics(
        movement_time_s=float(t[offset] - t[onset]),
        peak_speed_m_s=float(speed[peak]),
        time_to_peak_speed_s=float(t[peak] - t[onset]),
        n_speed_peaks=n_speed_peaks(speed),
        path_length_ratio=path_length_ratio(motion_estimate(x, _rate(t))),
    )


def n_speed_peaks(speed: np.ndarray, prominence: float = PEAK_FRACTION) -> int:
    """Local maxima of a speed profile (N,) standing out by ``prominence`` of its peak."""

    top = float(np.max(speed)) if len(speed) else 0.0
    if top <= 0.0:
        return 0
    padded = np.concatenate([[0.0], speed, [0.0]])  # a profile may start or end at speed
    return len(find_peaks(padded, prominence=prominence * top)[0])


def path_length_ratio(x: np.ndarray) -> float:
    """The path's length over the straight distance from its first to its last point
    (N, 3) [-]: 1 for a straight path, larger for a detour (1 without displacement)."""
    length = float(np.sum(np.linalg.norm(np.diff(x, axis=0), axis=1))) if len(x) > 1 else 0.0
    straight = float(np.linalg.norm(x[-1] - x[0])) if len(x) else 0.0
    return length / straight if straight > 1e-9 else 1.0


def goal_error(x: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """||x - x_g|| per sample [m], shape (N,)."""
    return np.asarray(np.linalg.norm(np.atleast_2d(x) - goal, axis=-1))


def n_oscillations(
    x: np.ndarray,
    subgoals: np.ndarray,
    radii: np.ndarray,
    rate_hz: float,
    deadband_m: float = 0.001,
    near_factor: float = 2.0,
) -> int:
    """Waypoint oscillation count N_osc: direction reversals of the motion near the
    admission spheres.

    The measured end-effector path (``x`` (N, 3), sampled at ``rate_hz``) is first reduced
    to its motion (:func:`motion_estimate`: sensor noise removed, every movement the arm
    can make kept). Each task axis of it is scanned for reversals of direction, with a
    deadband: a reversal counts only once the coordinate has moved back by more than
    ``deadband_m`` from its last extreme, so what noise survives the filter and
    sub-millimetre vibration are not chatter. A reversal counts when its turning point
    lies within ``near_factor`` times the admission radius of one of the reach's subgoals
    (``subgoals`` (M, 3), ``radii`` (M,)): the same rule for every progression strategy,
    whichever subgoal was active. N_osc is the sum over the three axes.
    """
    if len(subgoals) == 0:
        return 0
    x = motion_estimate(x, rate_hz)
    turns = [i for axis in range(3) for i in _turning_points(x[:, axis], deadband_m)]
    if not turns:
        return 0
    distance = np.linalg.norm(x[turns][:, None, :] - subgoals[None, :, :], axis=2)  # (T, M)
    return int(np.sum(np.any(distance <= near_factor * radii[None, :], axis=1)))


MOTION_CUTOFF_HZ = 10.0
"""Above every movement the controller commands: its shortest micro-step segment lasts
``min_segment_s`` = 0.08 s (a half-period of 6 Hz), and the fixed-frequency timer ticks
at 10 Hz (chatter at <= 5 Hz)."""


def motion_estimate(
    x: np.ndarray, rate_hz: float, cutoff_hz: float = MOTION_CUTOFF_HZ
) -> np.ndarray:
    """The end-effector's motion from its measured path (N, 3): a zero-phase 4th-order
    Butterworth low-pass at ``cutoff_hz``. White sensor noise keeps about
    sqrt(cutoff / Nyquist) of its amplitude (0.45 at 100 Hz); motion below the cutoff
    passes unchanged and undelayed. Paths too short to filter are returned as they are."""

    if cutoff_hz >= rate_hz / 2 or len(x) < 16:
        return x
    sos, zi = _low_pass(cutoff_hz, rate_hz)
    return _filtfilt(sos, zi, np.asarray(x, dtype=float), min(len(x) - 1, 27))


@functools.lru_cache(maxsize=16)
def _low_pass(cutoff_hz: float, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The filter's sections and their steady-state initial conditions (n_sections, 2),
    computed once per rate: designing them costs more than filtering a decision's path, and
    the RL reward counts oscillations at every decision."""
    sos = np.asarray(butter(4, cutoff_hz, fs=rate_hz, output="sos"))
    return sos, np.asarray(sosfilt_zi(sos))


def _filtfilt(sos: np.ndarray, zi: np.ndarray, x: np.ndarray, padlen: int) -> np.ndarray:
    """``scipy.signal.sosfiltfilt(sos, x, axis=0, padlen=padlen)`` with the initial
    conditions ``zi`` given (the same operations in the same order: bitwise its result)."""
    ext = np.concatenate((2 * x[:1] - x[padlen:0:-1], x,
                          2 * x[-1:] - x[-2 : -(padlen + 2) : -1]))  # fmt: skip
    signals = np.array(ext.T, order="C")  # one row per axis, filtered in place
    signals = _filter_rows(sos, signals, zi[None, :, :] * signals[:, :1, None])
    backwards = np.array(signals[:, ::-1], order="C")
    backwards = _filter_rows(sos, backwards, zi[None, :, :] * backwards[:, :1, None])
    y = backwards[:, ::-1].T
    return np.asarray(y[padlen:-padlen] if padlen > 0 else y)


def _filter_rows(sos: np.ndarray, rows: np.ndarray, zi: np.ndarray) -> np.ndarray:
    """Each row of ``rows`` (k, n) through the sections from the states ``zi`` (k, s, 2):
    SciPy's own filter loop, without its wrapper's reshaping (most of a short path's cost);
    the public ``sosfilt`` where the loop is not where it was."""
    if _sosfilt_rows is None:
        return np.asarray(sosfilt(sos, rows, axis=-1, zi=np.moveaxis(zi, 0, -2).copy())[0])
    _sosfilt_rows(sos, rows, np.ascontiguousarray(zi))
    return rows


def decisions_until_stable(choices: list[Any]) -> int:
    """Multi-model convergence: how many decisions passed before the choice in force at the
    end was made for good (0: the first choice was never changed)."""
    for k in range(len(choices) - 1, 0, -1):
        if choices[k] != choices[k - 1]:
            return k
    return 0


def _turning_points(signal: np.ndarray, deadband: float) -> list[int]:
    """Indices of the extremes at which ``signal`` reversed by more than ``deadband``."""
    turns: list[int] = []
    direction, extreme, extreme_i = 0, float(signal[0]), 0
    for i, value in enumerate(signal.tolist()):
        if (direction >= 0 and value > extreme) or (direction <= 0 and value < extreme):
            if direction == 0 and abs(value - float(signal[0])) > deadband:
                direction = 1 if value > signal[0] else -1
            if direction != 0:
                extreme, extreme_i = value, i
        elif direction != 0 and abs(value - extreme) > deadband:
            turns.append(extreme_i)
            direction, extreme, extreme_i = -direction, value, i
    return turns


def jerk(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Jerk [m/s^3] (N, 3) by differentiating the velocity twice (uniform sampling)."""
    dt = float(t[1] - t[0])
    return np.asarray(np.gradient(np.gradient(v, dt, axis=0), dt, axis=0))


def mechanical_work_j(q: np.ndarray, tau: np.ndarray, dt_s: float) -> float:
    """The effort E_effort of the paper's reward: the mechanical work sum |tau . dq/dt| dt
    [J] over a stretch of joint positions ``q`` (N, 6) [rad] and torques ``tau`` (N, 6)
    [N m] sampled every ``dt_s``; 0 for fewer than three samples."""
    if len(q) < 3:
        return 0.0
    dq = np.gradient(q, dt_s, axis=0)
    return float(np.sum(np.abs(np.sum(tau * dq, axis=1))) * dt_s)


def integrated_squared_jerk(t: np.ndarray, v: np.ndarray) -> float:
    """ISJ = integral of ||d^3x/dt^3||^2 dt [m^2/s^5]."""
    if len(t) < 3:
        return 0.0
    j = jerk(t, v)
    return float(np.sum(j**2) * (t[1] - t[0]))


def _speed(v: np.ndarray) -> np.ndarray:
    return np.asarray(np.linalg.norm(v, axis=1))


def _rate(t: np.ndarray) -> float:
    return 1.0 / float(t[1] - t[0]) if len(t) > 1 else 1.0


def spectral_arc_length(
    speed: np.ndarray,
    rate_hz: float,
    padding: int = 4,
    cutoff_hz: float = 10.0,
    threshold: float = 0.05,
) -> float:
    """SPARC, the spectral arc length of a speed profile (Balasubramanian et al. 2015,
    J NeuroEng Rehabil 12:112): minus the length of the normalised Fourier magnitude
    spectrum's curve, over the band from 0 up to where it last exceeds ``threshold``
    (at most ``cutoff_hz``), with the frequency axis normalised to that band. Smoother
    movements score closer to 0; it is independent of amplitude and duration. A Gaussian
    speed profile exp(-5 t^2), t in [-1, 1) at 100 Hz, scores -1.41403."""
    if len(speed) < 2 or float(np.max(np.abs(speed))) == 0.0:
        return 0.0
    n_fft = int(2 ** (math.ceil(math.log2(len(speed))) + padding))
    frequency = np.arange(n_fft) * rate_hz / n_fft
    magnitude = np.abs(np.fft.fft(speed, n_fft))
    magnitude = magnitude / magnitude.max()
    band = frequency <= cutoff_hz
    frequency, magnitude = frequency[band], magnitude[band]
    above = np.nonzero(magnitude >= threshold)[0]
    frequency = frequency[above[0] : above[-1] + 1]
    magnitude = magnitude[above[0] : above[-1] + 1]
    if len(frequency) < 2:
        return 0.0
    df = np.diff(frequency) / (frequency[-1] - frequency[0])
    return -float(np.sum(np.sqrt(df**2 + np.diff(magnitude) ** 2)))


def log_dimensionless_jerk(speed: np.ndarray, rate_hz: float) -> float:
    """LDLJ (Balasubramanian et al. 2015): -ln(D^3 / v_peak^2 * integral of (d^2 v/dt^2)^2
    dt) for a speed profile of duration D and peak v_peak. Smoother movements score
    higher (closer to 0). A Gaussian speed profile exp(-5 t^2), t in [-1, 1) at 100 Hz,
    scores -5.81636."""
    v_peak = float(np.max(np.abs(speed))) if len(speed) else 0.0
    if len(speed) < 3 or v_peak == 0.0:
        return 0.0
    dt = 1.0 / rate_hz
    duration = len(speed) * dt
    jerk_ = np.diff(speed, 2) / dt**2
    return -math.log(duration**3 / v_peak**2 * float(np.sum(jerk_**2)) * dt)


def human_error_rate(correct: list[bool] | np.ndarray) -> float:
    """Empirical share of human commands that pointed away from the goal (0 if none)."""
    flags = np.asarray(correct, dtype=bool)
    return float(1.0 - flags.mean()) if flags.size else 0.0


class Dwell:
    """A condition held for ``dwell_s`` (a press, not a fly-by); ``done`` stays true once
    it was."""

    def __init__(self, dwell_s: float) -> None:
        self.dwell_s = dwell_s
        self.entered_s: float | None = None
        self.done = False

    def update(self, t_s: float, holds: bool) -> bool:
        """True once the condition has held since ``dwell_s`` ago."""
        if not holds:
            self.entered_s = None
            return False
        if self.entered_s is None:
            self.entered_s = t_s
        held = t_s - self.entered_s >= self.dwell_s - 1e-9
        self.done |= held
        return held
