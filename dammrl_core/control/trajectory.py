"""Smooth joint references: a quintic from the current reference state to rest at q_{k+1}."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_JERK_PEAK_FACTOR = 1.875  # peak / mean speed of a rest-to-rest minimum-jerk profile


@dataclass(frozen=True)
class QuinticSegment:
    """Joint reference from (q0, v0, a0) at ``t0_s`` to (q1, 0, 0) at ``t0_s + duration_s``.

    Starting from the current reference state keeps q_ref, dq_ref and ddq_ref continuous
    when a step replaces one still in progress (the fixed-frequency baseline does that).
    """

    t0_s: float
    duration_s: float
    coeffs: np.ndarray  # (6, n_joints): q(tau) = sum_k coeffs[k] tau^k
    rest: tuple[np.ndarray, np.ndarray, np.ndarray] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        powers = self.duration_s ** np.arange(6)
        zeros = np.zeros(self.coeffs.shape[1])
        object.__setattr__(self, "rest", (powers @ self.coeffs, zeros, zeros))

    @classmethod
    def plan(
        cls,
        t0_s: float,
        duration_s: float,
        q0: np.ndarray,
        v0: np.ndarray,
        a0: np.ndarray,
        q1: np.ndarray,
    ) -> QuinticSegment:
        T = duration_s
        dq = q1 - q0 - v0 * T - a0 * T**2 / 2
        dv = -v0 - a0 * T
        da = -a0
        c3 = (10 * dq - 4 * dv * T + da * T**2 / 2) / T**3
        c4 = (-15 * dq + 7 * dv * T - da * T**2) / T**4
        c5 = (6 * dq - 3 * dv * T + da * T**2 / 2) / T**5
        return cls(t0_s, T, np.stack([q0, v0, a0 / 2, c3, c4, c5]))

    @classmethod
    def hold(cls, t0_s: float, q: np.ndarray) -> QuinticSegment:
        """A segment that stays at ``q`` (already finished at ``t0_s``)."""
        zeros = np.zeros_like(q)
        return cls(t0_s, 0.0, np.stack([q, zeros, zeros, zeros, zeros, zeros]))

    def moved_to(self, t0_s: float) -> QuinticSegment:
        """The same reference starting at ``t0_s`` (its shape does not depend on its start:
        bitwise the segment ``plan`` makes from the same states at ``t0_s``)."""
        return QuinticSegment(t0_s, self.duration_s, self.coeffs)

    @property
    def end_s(self) -> float:
        return self.t0_s + self.duration_s

    @property
    def target(self) -> np.ndarray:
        return self.rest[0]

    def finished(self, t_s: float) -> bool:
        return t_s >= self.t0_s + self.duration_s

    def sample(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, dq, ddq) of the reference at time ``t_s``; at rest on the target after the end."""
        if t_s >= self.t0_s + self.duration_s:
            return self.rest
        tau = max(t_s - self.t0_s, 0.0)
        t2 = tau * tau
        t3 = t2 * tau
        basis = np.array(  # rows: d^k/dtau^k of (1, tau, ..., tau^5) for k = 0, 1, 2
            (1.0, tau, t2, t3, t3 * tau, t3 * t2,
             0.0, 1.0, 2 * tau, 3 * t2, 4 * t3, 5 * t3 * tau,
             0.0, 0.0, 2.0, 6 * tau, 12 * t2, 20 * t3)
        ).reshape(3, 6)  # fmt: skip
        q, dq, ddq = basis @ self.coeffs
        return q, dq, ddq

    def sample_many(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``sample`` at each of ``times_s`` (n,), increasing: (q, dq, ddq), each
        (n, n_joints), the same numbers bit for bit (the same operations, row by row; the
        rows at rest copied from ``rest``)."""
        moving = int(np.searchsorted(times_s, self.t0_s + self.duration_s))  # then at rest
        sampled = np.empty((len(times_s), 3, self.coeffs.shape[1]))
        if moving:
            tau = np.maximum(times_s[:moving] - self.t0_s, 0.0)
            t2 = tau * tau
            t3 = t2 * tau
            basis = np.zeros((moving, 3, 6))
            basis[:, 0, 0] = basis[:, 1, 1] = 1.0
            basis[:, 2, 2] = 2.0
            basis[:, 0, 1] = tau
            basis[:, 0, 2] = t2
            basis[:, 0, 3] = t3
            basis[:, 0, 4] = t3 * tau
            basis[:, 0, 5] = t3 * t2
            basis[:, 1, 2] = 2 * tau
            basis[:, 1, 3] = 3 * t2
            basis[:, 1, 4] = 4 * t3
            basis[:, 1, 5] = 5 * t3 * tau
            basis[:, 2, 3] = 6 * tau
            basis[:, 2, 4] = 12 * t2
            basis[:, 2, 5] = 20 * t3
            sampled[:moving] = basis @ self.coeffs
        for k, value in enumerate(self.rest):
            sampled[moving:, k] = value
        return sampled[:, 0], sampled[:, 1], sampled[:, 2]


def segment_duration(
    dq: np.ndarray,
    dx_m: float,
    dq_max: np.ndarray,
    joint_speed_fraction: float,
    peak_speed_m_per_s: float,
    min_s: float,
) -> float:
    """Shortest minimum-jerk duration [s] keeping the peak joint speeds within
    ``joint_speed_fraction * dq_max`` and the peak Cartesian speed within the setting."""
    joint_s = MIN_JERK_PEAK_FACTOR * float(np.max(np.abs(dq) / (joint_speed_fraction * dq_max)))
    cartesian_s = MIN_JERK_PEAK_FACTOR * dx_m / peak_speed_m_per_s
    return max(min_s, joint_s, cartesian_s)
