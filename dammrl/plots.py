"""Figures of reaches (matplotlib, Agg backend: files only, no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Circle

from dammrl.episode import ReachResult

STYLE = {
    "fixed": {"color": "black", "label": "fixed-frequency"},
    "event": {"color": "tab:red", "label": "event-triggered"},
}
MM = 1000.0


def plot_reaches(results: list[ReachResult], goal_tolerance_m: float, path: Path) -> Path:
    """Fixed vs event trajectories: overview, the final approach with its subgoals and
    admission spheres, and the distance to the goal over time."""
    fig, axes = plt.subplots(2, 2, figsize=(12, 9.5), constrained_layout=True)
    (top, side), (zoom, distance) = axes
    task = results[0].task
    for result in results:
        style = STYLE[result.trigger]
        x = result.trajectory.x
        top.plot(x[:, 0] * MM, x[:, 1] * MM, color=style["color"], lw=1.2, label=style["label"])
        side.plot(x[:, 0] * MM, x[:, 2] * MM, color=style["color"], lw=1.2, label=style["label"])
        _plot_approach(zoom, result, style["color"], style["label"])
        _plot_distance(distance, result, style["color"], style["label"])
    for ax, (i, j), title in ((top, (0, 1), "top view"), (side, (0, 2), "side view")):
        _mark_task(ax, task.start, task.goal, goal_tolerance_m, i, j)
        ax.set_title(title)
        ax.set_xlabel("x (primary axis) [mm]")
        ax.set_ylabel(f"{'yz'[j - 1]} [mm]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(loc="best", fontsize=8)
    _mark_task(zoom, task.start, task.goal, goal_tolerance_m, 0, 1)
    _zoom_on_goal(zoom, task.goal, results)
    distance.axhline(
        goal_tolerance_m * MM,
        color="tab:green",
        ls="--",
        lw=1,
        label="goal tolerance $\\varepsilon_g$",
    )
    distance.set_xlabel("time [s]")
    distance.set_ylabel("distance to goal $\\|x - x_g\\|$ [mm]")
    distance.set_yscale("log")
    distance.set_title("convergence")
    distance.legend(loc="best", fontsize=8)
    fig.suptitle(_title(results))
    path = Path(path)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def _plot_approach(ax: Axes, result: ReachResult, color: str, label: str) -> None:
    """Final approach seen from above: path, subgoals and (event) admission spheres."""
    x = result.trajectory.x
    ax.plot(x[:, 0] * MM, x[:, 1] * MM, color=color, lw=1.0, label=label)
    subgoals = np.array([s.subgoal for s in result.steps]) if result.steps else np.zeros((0, 3))
    marker = "o" if result.trigger == "event" else "x"
    ax.plot(
        subgoals[:, 0] * MM,
        subgoals[:, 1] * MM,
        marker,
        color=color,
        ms=3,
        ls="none",
        label=f"{label} subgoals",
    )
    if result.trigger == "event":
        for step in result.steps:
            ax.add_patch(
                Circle(
                    (step.subgoal[0] * MM, step.subgoal[1] * MM),
                    step.radius_m * MM,
                    fill=False,
                    color=color,
                    lw=0.6,
                    alpha=0.5,
                )
            )


def _zoom_on_goal(ax: Axes, goal: np.ndarray, results: list[ReachResult]) -> None:
    span = 60.0  # mm around the goal
    ax.set_xlim(goal[0] * MM - span, goal[0] * MM + span)
    ax.set_ylim(goal[1] * MM - span, goal[1] * MM + span)
    ax.set_aspect("equal")
    ax.set_title("near the goal (top view): subgoals, admission spheres $\\varepsilon$")
    ax.set_xlabel("x (primary axis) [mm]")
    ax.set_ylabel("y [mm]")
    ax.legend(loc="upper left", fontsize=7)


def _plot_distance(ax: Axes, result: ReachResult, color: str, label: str) -> None:
    t, x = result.trajectory.t, result.trajectory.x
    ax.plot(t, np.linalg.norm(x - result.task.goal, axis=1) * MM, color=color, lw=1.0, label=label)


def _mark_task(
    ax: Axes, start: np.ndarray, goal: np.ndarray, tolerance_m: float, i: int, j: int
) -> None:
    ax.plot(start[i] * MM, start[j] * MM, "s", color="tab:blue", ms=6, label="start $x_s$")
    ax.plot(goal[i] * MM, goal[j] * MM, "*", color="tab:green", ms=10, label="goal $x_g$")
    ax.add_patch(
        Circle(
            (goal[i] * MM, goal[j] * MM),
            tolerance_m * MM,
            fill=False,
            color="tab:green",
            ls="--",
            lw=1,
        )
    )


def _title(results: list[ReachResult]) -> str:
    first = results[0]
    parts = [f"M_{first.model[0]},{first.model[1]}, seed {first.seed}"]
    for r in results:
        m = r.metrics
        parts.append(
            f"{r.trigger}: {m.outcome}, t={m.t_total_s:.1f} s, N_osc={m.n_osc}, "
            f"error={m.final_error_m * MM:.1f} mm"
        )
    return " | ".join(parts)
