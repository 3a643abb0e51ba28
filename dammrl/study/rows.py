"""What the judging reads: a reach as a flat row of figures, and a training run's log.

Part of the registered rules (``claims.RULE_FILES``): a column's definition decides a
verdict as surely as a threshold does.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dammrl.study.claims import EPS_G_RANGE_MM, eps_column, step_windows
from dammrl_core.metrics import decisions_until_stable, mechanical_work_j, n_oscillations

if TYPE_CHECKING:
    from dammrl.stack.runner import ReachResult

TRAINING_COLUMNS = ("q_human", "q_robot")


def reach_row(result: ReachResult, identity: dict[str, Any], runs: int,
              tolerance_m: float) -> dict[str, Any]:  # fmt: skip
    """The reach as a flat row: ``identity`` first (configuration, condition, seed, ...),
    ``runs`` the number of training runs of its configuration (0: it learns nothing),
    then the metrics and the figures the claims read, at every eps_g of the range
    (``tolerance_m``: the task's own goal tolerance, that of ``reached``)."""
    metrics = result.metrics.as_dict()
    human = [c.human_model for c in result.choices]
    robot = [c.robot_model for c in result.choices]
    n = len(result.choices)
    start_distance = float(np.linalg.norm(result.task.goal - result.task.start))
    row: dict[str, Any] = {
        **identity,
        "runs": runs,
        "model": f"{result.model[0]},{result.model[1]}",  # in force at the end
        **metrics,
        "t_success_s": metrics["t_total_s"] if metrics["success"] else None,
        "t_reached_s": first_within(result, tolerance_m),
        "n_osc_true": n_osc_true(result),
        "effort_j": effort(result),
        "human_stable_after": decisions_until_stable(human),
        "robot_stable_after": decisions_until_stable(robot),
        "stable_share": 1 - decisions_until_stable(list(zip(human, robot, strict=True))) / n
        if n
        else None,
        "step_mean_m": mean_step(result, 0.0, np.inf),
        "early_step_m": mean_step(result, *step_windows(0.0, start_distance)["early"]),
        "ik_latency_median_s": float(np.median(result.ik_latencies_s))
        if result.ik_latencies_s
        else None,
    }
    for eps_mm in EPS_G_RANGE_MM:
        eps_m = eps_mm / 1000
        windows = step_windows(eps_m, start_distance)
        t_within = first_within(result, eps_m)
        row[eps_column("reached", eps_mm)] = t_within is not None
        row[eps_column("t_reached", eps_mm)] = t_within
        row[eps_column("midlate_step", eps_mm)] = mean_step(result, *windows["midlate"])
        row[eps_column("late_step", eps_mm)] = mean_step(result, *windows["late"])
    return row


def first_within(result: ReachResult, tolerance_m: float) -> float | None:
    """When the measured end-effector first came within ``tolerance_m`` of the goal (the
    paper's success criterion), before the reach ended; None if it never did."""
    traj = result.trajectory
    kept = traj.t <= result.metrics.t_total_s + 1e-9
    within = np.linalg.norm(traj.x[kept] - result.task.goal, axis=1) <= tolerance_m
    return float(traj.t[kept][np.argmax(within)]) if within.any() else None


def n_osc_true(result: ReachResult) -> int | None:
    """N_osc on the noise-free path (simulation's ground truth), beside N_osc on the
    measured one: how much of the count is motion."""
    traj = result.trajectory
    kept = traj.t <= result.metrics.t_total_s + 1e-9
    x = traj.x_true[kept]
    if len(x) == 0 or not np.all(np.isfinite(x)):
        return None
    subgoals = np.array([s.subgoal for s in result.steps]).reshape(-1, 3)
    radii = np.array([s.radius_m for s in result.steps])
    rate = 1.0 / float(traj.t[1] - traj.t[0]) if len(traj.t) > 1 else 1.0
    return n_oscillations(x, subgoals, radii, rate)


def effort(result: ReachResult) -> float:
    """The reach's mechanical work [J] up to its end: the reward's E_effort, whole."""
    traj = result.trajectory
    kept = traj.t <= result.metrics.t_total_s + 1e-9
    dt = float(traj.t[1] - traj.t[0]) if len(traj.t) > 1 else 1.0
    return mechanical_work_j(traj.q[kept], traj.tau[kept], dt)


def mean_step(result: ReachResult, nearest_m: float, farthest_m: float) -> float | None:
    """Mean step magnitude [m] of the steps planned at a goal distance in
    (nearest, farthest]; None when there is none."""
    sizes = [s.steps_m.mean() for s in result.steps if nearest_m < s.goal_error_m <= farthest_m]
    return float(np.mean(sizes)) if sizes else None


def steps_of(result: ReachResult) -> np.ndarray:
    """(n, 2) per micro-step: distance to the goal when planned [m], mean step [m]."""
    rows = [(s.goal_error_m, float(s.steps_m.mean())) for s in result.steps]
    return np.array(rows, dtype=float).reshape(-1, 2)


def read_training(path: Path) -> dict[str, np.ndarray] | None:
    """A run's training log: the Q-value columns by episode (None: no readable log)."""
    try:
        with path.open() as f:
            rows = list(csv.DictReader(f))
        return {k: np.array([float(r[k]) for r in rows]) for k in TRAINING_COLUMNS}
    except (OSError, KeyError, ValueError):
        return None
