"""Inverse kinematics of the end-effector point: ikpy and pinocchio damped least squares.

Both solvers take a Cartesian target [m] (3,) and a seed [rad] (6,) and return joint
positions inside the joint limits. The controller accepts a solution only if it lands
within ``ik_accept_error_m`` of its target and does not jump away from the seed.

The latency model turns the solvers' compute time into simulated time: the processor time
of each solve actually run ('measured', the paper's mechanism produced rather than
injected; processor time, not wall time, so other work on a shared machine leaves it be,
but a faster processor does not), the time the same solve took on the reference machine
('reference': the solve's work, its forward-kinematics evaluations, times the reference's
cost per evaluation, with the reference's spread drawn from the seed: the mechanism of
'measured' without this computer's speed in the result), a lognormal draw independent of
the solve ('model', defaults fitted to solves timed by ``benchmarks/bench_core.py`` on the
2-core development machine), or none. Any of them can be scaled (a slower or faster
computer). Every latency that entered simulated time is kept (``IKLatency.spent_s``), and
a list of them replays a run exactly (``replay``): same solves, same latencies,
byte-identical reach.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np

from dammrl_core.dynamics import ArmModel
from dammrl_core.errors import ConfigurationError

IKSolverName = Literal["ikpy", "pinocchio"]
MAX_LATENCY_SCALE = 100.0  # a computer 100 times slower than the reference at most
LatencyMode = Literal["model", "measured", "reference", "zero"]

# (median [s], log-sigma) of solve times fitted by benchmarks/bench_core.py
FITTED_LATENCY: dict[IKSolverName, tuple[float, float]] = {
    "ikpy": (0.055, 0.57),
    "pinocchio": (0.00015, 0.7),
}


@dataclass(frozen=True)
class ReferenceCost:
    """What one forward-kinematics evaluation of a solve cost on the reference machine:
    a solve of n evaluations took n * per_evaluation_s * exp(sigma * z) there (z standard
    normal: the spread of its measured times about that line)."""

    per_evaluation_s: float
    sigma: float
    machine: str  # where the reference times were measured, and which solves


# Fitted by ``python -m dammrl.study.latency`` on the processor times study v2 measured
# and saved (git show 20e3687:docs/study/ik_latencies.json.gz), 40 reaches of each paper
# configuration replayed with each solve's evaluations counted (every replay matched):
# ikpy 4107 solves, log time on log evaluations R^2 0.78; damped least squares 3905
# solves, R^2 0.05 (a few iterations each: the time is mostly overhead, ~0.3 ms).
REFERENCE_COST: dict[IKSolverName, ReferenceCost] = {
    "ikpy": ReferenceCost(2.2226e-4, 0.265, "study v2's machine (2 cores)"),
    "pinocchio": ReferenceCost(9.057e-5, 0.326, "study v2's machine (2 cores)"),
}


@dataclass(frozen=True)
class IKResult:
    q: np.ndarray  # joint positions [rad] (6,)
    error_m: float  # ||FK(q) - target|| [m]
    compute_s: float  # wall time spent solving [s]
    cpu_s: float  # processor time this thread spent solving [s]: what another process's
    # load on the machine leaves unchanged (the 'measured' latency)
    evaluations: int = 0  # forward-kinematics evaluations: the solve's work, whatever the
    # machine (the 'reference' latency)


class IKSolver(Protocol):
    name: IKSolverName

    def solve(self, target: np.ndarray, q_seed: np.ndarray) -> IKResult: ...


def _search_box(
    q_seed: np.ndarray, q_lo: np.ndarray, q_hi: np.ndarray, max_step_rad: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Joint limits, narrowed to ``q_seed +- max_step_rad`` when a step bound is given.

    A redundant arm has many solutions; bounding the search around the seed keeps the
    solver on the branch the arm is on, so a micro-step never becomes a joint jump.
    """
    if max_step_rad is None:
        return q_lo, q_hi
    lo = np.maximum(q_lo, q_seed - max_step_rad)
    hi = np.minimum(q_hi, q_seed + max_step_rad)
    return np.minimum(lo, hi), np.maximum(lo, hi)


def _inverse3(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric 3x3 ``A`` by its adjugate. At this size numpy.linalg's call
    overhead is larger than the whole computation."""
    (a, d, e), (_, b, f), (_, _, c) = A.tolist()
    adj = np.array(
        [
            [b * c - f * f, e * f - d * c, d * f - e * b],
            [e * f - d * c, a * c - e * e, d * e - a * f],
            [d * f - e * b, d * e - a * f, a * b - d * d],
        ]
    )
    return np.asarray(adj / (a * adj[0, 0] + d * adj[0, 1] + e * adj[0, 2]))


class DampedLeastSquaresIK:
    """Position IK by damped least squares on pinocchio's Jacobian.

    dq = J# e + (I - J# J) z with J# = J^T (J J^T + lambda^2 I)^-1: the task step plus a
    null-space step z = posture_gain (q_mid - q) that uses the arm's three redundant DoF to
    drift toward mid-range, away from the joint limits, without moving the end-effector.
    Joints pinned at a bound are taken out of J so the others do the work.
    """

    name: IKSolverName = "pinocchio"

    def __init__(
        self,
        arm: ArmModel,
        damping: float = 1e-3,
        tolerance_m: float = 1e-6,
        max_iterations: int = 100,
        limit_margin_rad: float = 0.0,
        max_step_rad: float | None = None,
        posture_gain: float = 0.1,
    ) -> None:
        self.arm = arm
        self.max_step_rad = max_step_rad
        self.damping = damping
        self.tolerance_m = tolerance_m
        self.max_iterations = max_iterations
        self.posture_gain = posture_gain
        self.q_lo = arm.robot.q_min + limit_margin_rad
        self.q_hi = arm.robot.q_max - limit_margin_rad
        self.q_mid = (arm.robot.q_min + arm.robot.q_max) / 2
        self._damping_matrix = damping**2 * np.eye(3)

    def solve(self, target: np.ndarray, q_seed: np.ndarray) -> IKResult:
        start, start_cpu = time.perf_counter(), time.thread_time()
        lo, hi = _search_box(q_seed, self.q_lo, self.q_hi, self.max_step_rad)
        q = np.minimum(np.maximum(q_seed, lo), hi)
        evaluations = 0
        for _ in range(self.max_iterations):
            x, J = self.arm.ee_position_and_jacobian(q)
            evaluations += 1
            error = target - x
            if error @ error < self.tolerance_m**2:
                break
            dq = self._step(J, error, q)
            blocked = (q <= lo) & (dq < 0) | (q >= hi) & (dq > 0)
            if np.logical_or.reduce(blocked):  # pinned at a bound: let the others do the work
                J[:, blocked] = 0.0
                dq = self._step(J, error, q)
                dq[blocked] = 0.0
            q = np.minimum(np.maximum(q + dq, lo), hi)
        error_m = float(np.linalg.norm(target - self.arm.ee_position(q)))
        return _result(q, error_m, start, start_cpu, evaluations)

    def _step(self, J: np.ndarray, error: np.ndarray, q: np.ndarray) -> np.ndarray:
        J_pinv = J.T @ _inverse3(J @ J.T + self._damping_matrix)  # (6, 3)
        posture = self.posture_gain * (self.q_mid - q)
        return np.asarray(J_pinv @ error + posture - J_pinv @ (J @ posture))


class IkpyIK:
    """Position IK by ikpy's bounded least-squares optimisation (the paper's solver)."""

    name: IKSolverName = "ikpy"

    def __init__(
        self, arm: ArmModel, limit_margin_rad: float = 0.0, max_step_rad: float | None = None
    ) -> None:
        self.arm = arm
        self.chain = arm.robot.ikpy_chain()
        self.active = np.asarray(self.chain.active_links_mask, dtype=bool)
        links = zip(self.chain.links, self.active, strict=True)
        self.active_links = [link for link, on in links if on]
        self.q_lo = arm.robot.q_min + limit_margin_rad
        self.q_hi = arm.robot.q_max - limit_margin_rad
        self.max_step_rad = max_step_rad
        self.evaluations = 0
        forward = self.chain.forward_kinematics

        def counted(*args: Any, **kwargs: Any) -> Any:
            self.evaluations += 1  # ikpy's optimiser evaluates the chain once per call
            return forward(*args, **kwargs)

        self.chain.forward_kinematics = counted

    def solve(self, target: np.ndarray, q_seed: np.ndarray) -> IKResult:
        start, start_cpu = time.perf_counter(), time.thread_time()
        lo, hi = _search_box(q_seed, self.q_lo, self.q_hi, self.max_step_rad)
        for link, low, high in zip(self.active_links, lo, hi, strict=True):
            link.bounds = (float(low), float(high))
        full = np.zeros(len(self.chain.links))
        full[self.active] = np.clip(q_seed, lo, hi)
        self.evaluations = 0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # ikpy warns about its own URDF conventions
            solution = self.chain.inverse_kinematics(target_position=target, initial_position=full)
        q = np.asarray(solution)[self.active]
        evaluations = self.evaluations
        error_m = float(np.linalg.norm(target - self.arm.ee_position(q)))
        return _result(q, error_m, start, start_cpu, evaluations)


def _result(q: np.ndarray, error_m: float, start: float, start_cpu: float,
            evaluations: int) -> IKResult:  # fmt: skip
    return IKResult(q, error_m, time.perf_counter() - start, time.thread_time() - start_cpu,
                    evaluations)  # fmt: skip


def make_ik_solver(
    name: IKSolverName, arm: ArmModel, limit_margin_rad: float, max_step_rad: float | None
) -> IKSolver:
    if name == "ikpy":
        return IkpyIK(arm, limit_margin_rad, max_step_rad)
    return DampedLeastSquaresIK(arm, limit_margin_rad=limit_margin_rad, max_step_rad=max_step_rad)


class IKLatency:
    """Simulated-time cost of one IK solve [s]; every cost handed out is kept in
    ``spent_s``, in order, so a run's latencies can be saved and replayed."""

    def __init__(
        self,
        mode: LatencyMode,
        solver: IKSolverName,
        rng: np.random.Generator,
        median_s: float | None = None,
        sigma: float | None = None,
        replay: Sequence[float] | None = None,
        scale: float = 1.0,
    ) -> None:
        """``solver``: whose fitted distribution 'model' draws from, whose reference cost
        'reference' charges; ``replay``: the latencies [s] a run spent (its ``spent_s``),
        handed out again in order instead of the mode's (the solves still run: their joint
        solutions); ``scale``: every latency of the mode times this (a computer this many
        times slower; a replay is not scaled)."""
        if not 0.0 < scale <= MAX_LATENCY_SCALE:
            raise ConfigurationError(
                f"ik_latency_scale must be in (0, {MAX_LATENCY_SCALE:g}], got {scale!r}"
            )
        fitted_median, fitted_sigma = FITTED_LATENCY[solver]
        self.mode = mode
        self.solver = solver
        self.scale = scale
        self.median_s = fitted_median if median_s is None else median_s
        self.sigma = fitted_sigma if sigma is None else sigma
        self.rng = rng
        self.replay = None if replay is None else [_latency(v) for v in replay]
        self.spent_s: list[float] = []
        self.evaluations: list[int] = []  # each solve's work, beside what it cost

    def __call__(self, measured_s: float, evaluations: int = 0) -> float:
        """The simulated time of a solve that took ``measured_s`` of processor time here
        and ``evaluations`` forward-kinematics evaluations."""
        latency = self._next(measured_s, evaluations)
        self.spent_s.append(latency)
        self.evaluations.append(int(evaluations))
        return latency

    def _next(self, measured_s: float, evaluations: int) -> float:
        if self.replay is not None:
            if len(self.spent_s) >= len(self.replay):
                raise ConfigurationError(
                    f"the replayed IK latencies ran out at solve {len(self.spent_s) + 1} "
                    f"(recorded: {len(self.replay)}): they are not this reach's"
                )
            return self.replay[len(self.spent_s)]
        if self.mode == "zero":
            return 0.0
        if self.mode == "measured":
            return self.scale * measured_s
        if self.mode == "reference":
            cost = REFERENCE_COST[self.solver]
            spread = np.exp(cost.sigma * self.rng.standard_normal())
            return float(self.scale * evaluations * cost.per_evaluation_s * spread)
        return float(self.scale * self.median_s * np.exp(self.sigma * self.rng.standard_normal()))


def _latency(value: float) -> float:
    latency = float(value)
    if not 0.0 <= latency < 60.0:  # NaN fails too
        raise ConfigurationError(f"a replayed IK latency must be 0-60 s, got {value!r}")
    return latency
