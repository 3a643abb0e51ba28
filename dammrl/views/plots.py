"""Figures of reaches (matplotlib, Agg backend: files only, no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Circle, Rectangle

from dammrl.stack.recording import SessionTraces
from dammrl.stack.runner import ReachResult
from dammrl_core.robot.scene import SceneLayout

COLORS = {"fixed": "black", "event": "tab:red"}  # the paper's colours
LABELS = {"fixed": "fixed-frequency", "event": "event-triggered"}
AXES = {0: "x (primary)", 1: "y", 2: "z"}
MM = 1000.0
ZOOM_RADIUS_M = 0.05  # the close-up shows the path within this distance of the goal


def plot_reaches(results: list[ReachResult], goal_tolerance_m: float, path: Path,
                 layout: SceneLayout | None = None) -> Path:  # fmt: skip
    """One reach per progression strategy, same start and goal: overview, close-ups of the
    final approach with subgoals and admission spheres, and convergence over time. The
    goal's button cap is drawn (``layout``): success is pressing it, so a path may end
    tens of millimetres from the goal's star, on the cap's rim."""
    layout = layout or SceneLayout()
    fig, axes = plt.subplots(2, 3, figsize=(16, 9.5), constrained_layout=True)
    (top, side, distance), (zoom_top, zoom_side, primary) = axes
    task = results[0].task
    for ax, plane, zoom in (
        (top, (0, 1), False),
        (side, (0, 2), False),
        (zoom_top, (0, 1), True),
        (zoom_side, (0, 2), True),
    ):
        for n, result in enumerate(results):
            _plot_path(ax, result, plane, with_subgoals=zoom)
            _mark_fingertip(ax, result, plane, layout.fingertip_radius_m, labelled=n == 0)
        _mark_button(ax, task.goal, layout, plane)
        _mark_task(ax, task.start, task.goal, goal_tolerance_m, plane, with_start=not zoom)
        if zoom:
            _zoom(ax, results, plane, goal_tolerance_m)
        view = "top" if plane[1] == 1 else "side"
        ax.set_title(
            f"{view} view" + (", near the goal: subgoals and admission spheres" if zoom else "")
        )
        ax.set_xlabel(f"{AXES[plane[0]]} [mm]")
        ax.set_ylabel(f"{AXES[plane[1]]} [mm]")
        ax.legend(loc="best", fontsize=7)
    for result in results:
        _plot_distance(distance, result)
        _plot_primary(primary, result)
    distance.axhline(
        goal_tolerance_m * MM,
        color="tab:green",
        ls="--",
        lw=1,
        label="goal tolerance $\\varepsilon_g$",
    )
    distance.set(
        xlabel="time [s]",
        ylabel="distance to goal $\\|x - x_g\\|$ [mm]",
        yscale="log",
        title="convergence",
    )
    distance.legend(loc="best", fontsize=7)
    primary.axhline(0.0, color="tab:green", lw=0.8)
    primary.set(
        xlabel="time before the end of the reach [s]",
        ylabel="primary-axis error $x - x_g$ [mm]",
        title="primary axis: last 4 s (dots: subgoals)",
    )
    primary.set_xlim(-4.0, 0.1)
    primary.legend(loc="best", fontsize=7)
    fig.suptitle(_title(results))
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _plot_path(ax: Axes, result: ReachResult, plane: tuple[int, int], with_subgoals: bool) -> None:
    i, j = plane
    color, label = COLORS[result.trigger], LABELS[result.trigger]
    x = result.trajectory.x
    ax.plot(x[:, i] * MM, x[:, j] * MM, color=color, lw=1.1, label=label)
    if not with_subgoals or not result.steps:
        return
    subgoals = np.array([s.subgoal for s in result.steps])
    marker = "o" if result.trigger == "event" else "x"
    ax.plot(
        subgoals[:, i] * MM,
        subgoals[:, j] * MM,
        marker,
        color=color,
        ms=3.5,
        ls="none",
        label=f"{label} subgoals",
    )
    if result.trigger == "event":  # the fixed baseline has no admission sphere
        for step in result.steps:
            ax.add_patch(
                Circle(
                    (step.subgoal[i] * MM, step.subgoal[j] * MM),
                    step.radius_m * MM,
                    fill=False,
                    color=color,
                    lw=0.6,
                    alpha=0.45,
                )
            )


def _zoom(ax: Axes, results: list[ReachResult], plane: tuple[int, int], tolerance_m: float) -> None:
    """Frame the samples within ZOOM_RADIUS_M of the goal and the goal ball, equal scale."""
    goal = results[0].task.goal
    near = np.concatenate(
        [
            r.trajectory.x[np.linalg.norm(r.trajectory.x - goal, axis=1) < ZOOM_RADIUS_M]
            for r in results
        ]
        + [goal[None, :]]
    )
    lo, hi = near[:, plane].min(axis=0) * MM - 8, near[:, plane].max(axis=0) * MM + 8
    half = max(hi - lo) / 2
    centre = (lo + hi) / 2
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal")


def _plot_distance(ax: Axes, result: ReachResult) -> None:
    t, x = result.trajectory.t, result.trajectory.x
    ax.plot(
        t,
        np.linalg.norm(x - result.task.goal, axis=1) * MM,
        color=COLORS[result.trigger],
        lw=1.0,
        label=LABELS[result.trigger],
    )


def _plot_primary(ax: Axes, result: ReachResult) -> None:
    t, x = result.trajectory.t, result.trajectory.x
    end, goal = t[-1], result.task.goal[0]
    color = COLORS[result.trigger]
    ax.plot(t - end, (x[:, 0] - goal) * MM, color=color, lw=1.0, label=LABELS[result.trigger])
    starts = np.array([s.start_s for s in result.steps]) - end
    subgoals = (np.array([s.subgoal[0] for s in result.steps]) - goal) * MM
    ax.plot(starts, subgoals, "o", color=color, ms=3, alpha=0.7)


def _mark_fingertip(ax: Axes, result: ReachResult, plane: tuple[int, int], radius_m: float,
                    labelled: bool) -> None:  # fmt: skip
    """The fingertip where the reach ended: the path is its centre, so a press shows as the
    fingertip's disc touching the cap, not as a path that stops short of it."""
    i, j = plane
    end = result.trajectory.x[-1] * MM
    label = "fingertip at the end" if labelled else None
    ax.add_patch(Circle((end[i], end[j]), radius_m * MM, color=COLORS[result.trigger],
                        alpha=0.15, lw=1.2, label=label))  # fmt: skip


def _mark_button(ax: Axes, goal: np.ndarray, layout: SceneLayout, plane: tuple[int, int]) -> None:
    """The cap the fingertip must press: a disc seen from above, a slab from the side (its
    top, and the fingertip's centre when it touches it, dotted)."""
    i, j = plane
    if j == 1:  # top view
        ax.add_patch(Circle((goal[i] * MM, goal[j] * MM), layout.cap_radius_m * MM,
                            color="tab:red", alpha=0.18, lw=0, label="button cap"))  # fmt: skip
        return
    top = layout.cap_top_z_m
    corner = ((goal[i] - layout.cap_radius_m) * MM, (top - layout.cap_height_m) * MM)
    width, height = 2 * layout.cap_radius_m * MM, layout.cap_height_m * MM
    ax.add_patch(Rectangle(corner, width, height, color="tab:red", alpha=0.18, lw=0,
                           label="button cap"))  # fmt: skip
    touch = (top + layout.fingertip_radius_m) * MM
    ax.axhline(touch, color="tab:red", lw=0.8, ls=":", label="fingertip on the cap")


def _mark_task(
    ax: Axes,
    start: np.ndarray,
    goal: np.ndarray,
    tolerance_m: float,
    plane: tuple[int, int],
    with_start: bool,
) -> None:
    i, j = plane
    if with_start:
        ax.plot(start[i] * MM, start[j] * MM, "s", color="tab:blue", ms=6, label="start $x_s$")
    ax.plot(goal[i] * MM, goal[j] * MM, "*", color="tab:green", ms=11, label="goal $x_g$")
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
    parts = [f"$M_{{{first.model[0]},{first.model[1]}}}$, seed {first.seed}"]
    for r in results:
        m = r.metrics
        parts.append(
            f"{LABELS[r.trigger]}: {m.outcome} in {m.t_total_s:.1f} s, "
            f"$N_{{osc}}$ = {m.n_osc}, final error {m.final_error_m * MM:.1f} mm"
        )
    return "   |   ".join(parts)


def plot_session(traces: SessionTraces, goal_tolerance_m: float, title: str, path: Path) -> Path:
    """The paper's S2 figure: the human's pressure input above the end-effector error."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(13, 6.5), sharex=True)
    _plot_pressure(top, traces)
    _plot_error(bottom, traces, goal_tolerance_m)
    for ax in (top, bottom):
        for t, _ in traces.episodes:
            ax.axvline(t, color="0.6", lw=0.8, ls=":")
        ax.grid(alpha=0.3)
    _label_episodes(top, traces.episodes)
    bottom.set_xlabel("time [s]")
    outcomes = ", ".join(f"{r.episode}: {r.outcome} {r.t_total_s:.1f} s" for _, r in traces.results)
    fig.suptitle(f"{title}\n{outcomes}" if outcomes else title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


def _label_episodes(ax: Axes, episodes: list[tuple[float, int]], gap: float = 0.05) -> None:
    """Each episode's number above its start line, leaving out a label that would touch the
    previous one (closer than ``gap`` of the axis)."""
    if not episodes:
        return
    low, high = ax.get_xlim()
    span, last = max(high - low, 1e-9), -np.inf
    for t, number in episodes:
        if (t - last) / span < gap:
            continue
        # inside the axes, under its top: above it the label would run into the title
        ax.annotate(f"ep. {number}", (t, 1.0), xycoords=("data", "axes fraction"),
                    xytext=(2, -2), textcoords="offset points", fontsize=7, color="0.35",
                    va="top", ha="left")  # fmt: skip
        last = t


DECISION_STYLES = {  # (u_h, human model) -> marker, colour, fill, label
    (1, 1): ("^", "tab:red", "full", "+1 firm, quick (E_big)"),
    (1, 2): ("^", "tab:red", "none", "+1 firm, held (E_small)"),
    (-1, 1): ("v", "black", "full", "-1 light, quick (E_big)"),
    (-1, 2): ("v", "black", "none", "-1 light, held (E_small)"),
}


def _plot_pressure(ax: Axes, traces: SessionTraces) -> None:
    """The pressure with each decision marked above it; without a pressure sensor (a
    simulated human, a wearable source) the decisions themselves: u_h = +1 or -1."""
    pressure = len(traces.pressure) > 0
    if pressure:
        ax.plot(traces.pressure_t, traces.pressure, color="tab:blue", lw=0.9, label="pressure")
        unit = "normalised (0 rest, 1 firm)" if traces.pressure_normalised else "raw ADC counts"
        ax.set_ylabel(f"pressure\n{unit}")
        marker_y = float(np.max(traces.pressure)) * 1.12
        ax.set_ylim(top=marker_y * 1.1)
        ax.set_title("primary-axis input: one press = one decision (marked as the press ends)")
    else:
        ax.set_ylabel("command $u_h$")
        ax.set_yticks([-1, 1], ["-1", "+1"])
        ax.set_ylim(-1.6, 1.6)
        ax.set_title("primary-axis commands (no pressure sensor in this recording)")
    for (u_h, model), (marker, color, fill, label) in DECISION_STYLES.items():
        times = [t for t, i in traces.decisions if (i.u_h, i.human_model) == (u_h, model)]
        if times:
            y = [marker_y if pressure else u_h] * len(times)
            ax.plot(times, y, marker, color=color, fillstyle=fill, ms=7, mew=1.3, ls="none",
                    label=label)  # fmt: skip
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)


def _plot_error(ax: Axes, traces: SessionTraces, goal_tolerance_m: float) -> None:
    t, e = traces.error_t, traces.error_m * MM
    starts = [start for start, _ in traces.episodes]
    breaks = np.searchsorted(t, starts)  # no line across the jump to the next goal
    t, e = np.insert(t, breaks, np.nan), np.insert(e, breaks, np.nan, axis=0)
    if len(t):
        for axis, color in zip(range(3), ("tab:red", "tab:green", "tab:blue"), strict=True):
            label = f"{'xyz'[axis]} error" + (" (primary)" if axis == 0 else "")
            ax.plot(t, e[:, axis], color=color, lw=1.0, label=label)
        ax.plot(t, np.linalg.norm(e, axis=1), color="k", lw=1.2, label="|error|")
    ax.axhspan(-goal_tolerance_m * MM, goal_tolerance_m * MM, color="tab:green", alpha=0.12,
               label=f"goal tolerance {goal_tolerance_m * MM:.0f} mm")  # fmt: skip
    ax.set_ylabel("end-effector - goal [mm]")
    ax.set_title("spatial error between the end-effector and the target")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
