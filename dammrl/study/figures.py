"""The study's figures (PNG, matplotlib Agg): the paper's figures and a summary chart."""

from __future__ import annotations

import csv
import itertools
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Rectangle
from matplotlib.ticker import MaxNLocator

from dammrl.study.configs import CONDITIONS, EVENT, FIXED, R1, R2, Configuration, checkpoint_file
from dammrl.study.inference import unit_values
from dammrl.study.run import Job, Record, reach
from dammrl.study.stats import Estimate, t_mean, wilson
from dammrl_core.robot.scene import SceneLayout

MM = 1000.0
SUMMARY_METRICS = (
    ("success", "success (button pressed) [%]", 100.0, True),
    ("reached", "reached, ||x - x_g|| <= eps_g [%]", 100.0, True),
    ("t_total_s", "total time [s]", 1.0, False),
    ("n_osc", "N_osc per reach", 1.0, False),
    ("n_osc_per_step", "oscillations per step", 1.0, False),
    ("final_error_m", "final error [mm]", MM, False),
    ("sparc", "SPARC (0: smoothest)", 1.0, False),
    ("ldlj", "LDLJ (higher: smoother)", 1.0, False),
    ("jerk_isj", "ISJ [10³ m²/s⁵]", 1e-3, False),
)
DISTANCE_BINS_M = np.array([0.0, 0.01, 0.02, 0.04, 0.08, 0.16, 0.5])


def describe(rows: list[dict[str, Any]], metric: str, rate: bool = False) -> Estimate:
    """The mean of ``metric`` over ``rows`` (one configuration) with a 95 % interval that
    respects where it varies: a t-interval over training runs (each run's mean) when the
    configuration has several, else over reaches (a rate of one run: Wilson)."""
    kept = [r for r in rows if r.get(metric) is not None]
    if not kept:
        return t_mean(np.empty(0))
    values = np.array([float(r[metric]) for r in kept])
    if max(int(r.get("runs") or 0) for r in kept) > 1:
        runs = np.array([int(r.get("run") or 0) for r in kept])
        e = t_mean(unit_values(values, runs))
        return Estimate(e.value, max(e.low, 0.0), min(e.high, 1.0), e.n) if rate else e
    if rate:
        return wilson(int(values.sum()), values.size)
    return t_mean(values)


def summary_chart(records: list[Record], configurations: list[Configuration],
                  conditions: tuple[str, ...], path: Path) -> Path:  # fmt: skip
    """Every metric per configuration with its 95 % interval (over training runs for a
    learned configuration), the conditions side by side."""
    keys = [c.key for c in configurations]
    fig, axes = plt.subplots(3, 3, figsize=(15, 12), constrained_layout=True)
    width = 0.8 / len(conditions)
    for ax, (metric, title, scale, rate) in zip(axes.flat, SUMMARY_METRICS, strict=True):
        for k, condition in enumerate(conditions):
            offset = (k - (len(conditions) - 1) / 2) * width
            means, lows, highs = [], [], []
            for key in keys:
                rows = [
                    r.row
                    for r in records
                    if r.row["configuration"] == key and r.row["condition"] == condition
                ]
                e = describe(rows, metric, rate)
                means.append(e.value * scale)
                lows.append((e.value - e.low) * scale)
                highs.append((e.high - e.value) * scale)
            if not np.all(np.isnan(means)):
                ax.bar(np.arange(len(keys)) + offset, means, width, yerr=[lows, highs],
                       capsize=2, label=condition)  # fmt: skip
        ax.set_title(title)
        ax.set_xticks(range(len(keys)), keys, rotation=60, ha="right", fontsize=8)
    handles, labels = axes.flat[0].get_legend_handles_labels()  # below the panels, on no bar
    fig.legend(handles, labels, loc="outside lower center", ncols=len(conditions), fontsize=9)
    fig.suptitle(
        "Every configuration on the held-out seeds (95 % intervals: t over training "
        "runs for a learned configuration, over reaches otherwise)"
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def trajectory_figure(configurations: list[Configuration], seed: int, path: Path) -> Path:
    """The paper's trajectory figure: the end-effector near the subgoals, fixed-frequency
    (black) against event-triggered DAMMRL (red), on one seed."""
    by_key = {c.key: c for c in configurations}
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True,
                             width_ratios=(1.7, 1))  # the close-up is square  # fmt: skip
    for key, color in ((FIXED, "black"), (R2, "tab:red")):
        if key not in by_key:
            continue
        result = reach(Job(by_key[key], seed, "nominal"))
        traj, goal = result.trajectory, result.task.goal
        error = np.linalg.norm(traj.x - goal, axis=1) * MM
        axes[0].plot(traj.t, error, color=color, lw=1.2, label=by_key[key].label)
        for step in result.steps:
            axes[0].plot(step.start_s, np.linalg.norm(step.subgoal - goal) * MM, "o",
                         color=color, ms=3, alpha=0.6)  # fmt: skip
        axes[1].plot((traj.x[:, 0] - goal[0]) * MM, (traj.x[:, 2] - goal[2]) * MM, color=color,
                     lw=1.2, label=by_key[key].label)  # fmt: skip
        subgoals = np.array([s.subgoal - goal for s in result.steps]).reshape(-1, 3) * MM
        axes[1].plot(subgoals[:, 0], subgoals[:, 2], "o", color=color, ms=3, alpha=0.6)
    axes[0].set(xlabel="time [s]", ylabel="distance to the goal [mm]", yscale="log",
                title=f"seed {seed}: distance (dots: subgoals when started)")  # fmt: skip
    _button_side_view(axes[1])
    axes[1].set(xlabel="x - x_g [mm]", ylabel="z - z_g [mm]", xlim=(-60, 20), ylim=(-20, 60),
                title="near the goal (x-z plane)", aspect="equal")  # fmt: skip
    axes[0].legend(fontsize=8)
    axes[1].legend(fontsize=8, loc="upper right")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _button_side_view(ax: Axes) -> None:
    """The goal's button cap seen from the side, relative to x_g: success is a press, so a
    reach may end on the cap's rim, tens of millimetres from x_g."""
    layout = SceneLayout()
    top = (layout.goal_press_depth_m - layout.fingertip_radius_m) * MM  # cap top - z_g
    ax.add_patch(Rectangle((-layout.cap_radius_m * MM, top - layout.cap_height_m * MM),
                           2 * layout.cap_radius_m * MM, layout.cap_height_m * MM,
                           color="tab:red", alpha=0.18, lw=0, label="button cap"))  # fmt: skip
    ax.axhline(layout.goal_press_depth_m * MM, color="tab:red", lw=0.8, ls=":",
               label="fingertip on the cap")  # fmt: skip


def step_modulation_figure(records: list[Record], path: Path) -> Path:
    """Reward 1 vs Reward 2: the step magnitude the robot agent chose against the distance
    to the goal (each training run's mean, thin, and their mean with a t-interval over
    runs), and the number of steps planned per reach."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    centres = (DISTANCE_BINS_M[:-1] + DISTANCE_BINS_M[1:]) / 2 * 100
    for key, label, color in ((R1, "Reward 1", "tab:blue"), (R2, "Reward 2", "tab:orange")):
        mine = [r for r in records
                if r.row["configuration"] == key and r.row["condition"] == "nominal"]  # fmt: skip
        if not mine:
            continue
        runs = sorted({int(r.row.get("run") or 0) for r in mine})
        per_run = np.array([_binned_steps([r for r in mine if (r.row.get("run") or 0) == k])
                            for k in runs])  # (runs, bins)  # fmt: skip
        for curve in per_run:
            left.plot(centres, curve * MM, "-", color=color, lw=0.6, alpha=0.35)
        stats = [t_mean(per_run[:, b]) for b in range(per_run.shape[1])]
        left.plot(centres, [s.value * MM for s in stats], "o-", color=color,
                  label=f"{label} ({len(runs)} training runs)")  # fmt: skip
        if len(runs) > 1:
            left.fill_between(centres, [s.low * MM for s in stats],
                              [s.high * MM for s in stats], color=color, alpha=0.2)  # fmt: skip
        counts = [r.row["n_steps"] for r in mine]
        right.hist(counts, bins=range(0, max(counts) + 2), color=color, alpha=0.5, label=label)
    left.set(xscale="log", xlabel="distance to the goal when planned [cm]",
             ylabel="mean step magnitude [mm]",
             title="learned step-size modulation (band: 95 % t over runs)")  # fmt: skip
    right.set(xlabel="micro-steps planned in a reach", ylabel="reaches",
              title="planned step counts")  # fmt: skip
    right.yaxis.set_major_locator(MaxNLocator(integer=True))  # counts of reaches
    left.legend()
    right.legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _binned_steps(records: list[Record]) -> np.ndarray:
    """The mean step [m] planned in each distance bin over ``records`` (NaN: none)."""
    steps = np.concatenate([r.steps for r in records]) if records else np.empty((0, 2))
    means = []
    for a, b in itertools.pairwise(DISTANCE_BINS_M):
        chosen = steps[(steps[:, 0] >= a) & (steps[:, 0] < b), 1]
        means.append(float(chosen.mean()) if chosen.size else np.nan)
    return np.array(means)


def latency_figure(records: list[Record], conditions: tuple[str, ...], path: Path
                   ) -> Path | None:  # fmt: skip
    """How configurations 1 and 2 depend on solve time: N_osc per reach and final error
    against the median IK latency of each ikpy condition that ran (the reference machine's
    times, scaled, and this computer's when measured), 95 % t-intervals over reaches."""
    timed = [c for c in conditions if c.startswith("ikpy-") and c != "ikpy-drawn"]
    if len(timed) < 2:
        return None
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), constrained_layout=True)
    panels = (("n_osc", "N_osc per reach", 1.0), ("final_error_m", "final error [mm]", MM),
              ("success", "success (pressed) [%]", 100.0))  # fmt: skip
    for key, color in ((FIXED, "black"), (EVENT, "tab:red")):
        points = []
        for condition in timed:
            rows = [
                r.row
                for r in records
                if r.row["configuration"] == key and r.row["condition"] == condition
            ]
            median = [r["ik_latency_median_s"] for r in rows if r.get("ik_latency_median_s")]
            if rows and median:
                points.append((float(np.median(median)) * MM, condition, rows))
        points.sort(key=lambda p: p[0])
        for ax, (metric, title, scale) in zip(axes, panels, strict=True):
            estimates = [describe(rows, metric, metric == "success") for _, _, rows in points]
            x = [p[0] for p in points]
            ax.errorbar(x, [e.value * scale for e in estimates],
                        yerr=[[(e.value - e.low) * scale for e in estimates],
                              [(e.high - e.value) * scale for e in estimates]],
                        fmt="o-", color=color, capsize=3, label=key)  # fmt: skip
            for xi, e, (_, condition, _) in zip(x, estimates, points, strict=True):
                if condition == "ikpy-measured":
                    ax.annotate(
                        "this computer",
                        (xi, e.value * scale),
                        fontsize=7,
                        textcoords="offset points",
                        xytext=(4, -10),
                    )
            ax.set(xscale="log", xlabel="median IK solve time [ms]", title=title)
    axes[0].legend()
    fig.suptitle(
        "Configurations 1 (fixed-frequency) and 2 (event trigger) against solve time "
        "(ikpy in the loop; " + ", ".join(CONDITIONS[c].key for c in timed) + ")"
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def training_figure(runs: dict[str, tuple[Path, ...]], path: Path) -> Path | None:
    """Training curves of both agents under both rewards (each run's training.csv)."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 4), constrained_layout=True)
    drawn = False
    for (label, checkpoints), color in zip(runs.items(), ("tab:blue", "tab:orange"), strict=False):
        for checkpoint in checkpoints:
            log = checkpoint_file(checkpoint).parent / "training.csv"
            if not log.exists():
                continue
            with log.open() as f:
                rows = list(csv.DictReader(f))
            episode = np.array([float(r["episode"]) for r in rows])
            for ax, column in zip(axes, ("ret", "q_human", "q_robot"), strict=True):
                ax.plot(episode, _smooth(np.array([float(r[column]) for r in rows])),
                        color=color, lw=1, label=label)  # fmt: skip
                label = "_"  # one legend entry per reward
            drawn = True
    if not drawn:
        plt.close(fig)
        return None
    panels = (("episode return (moving mean)", "return (reward units)"),
              ("human agent (radius i)", "mean max Q (reward units)"),
              ("robot agent (step vector j)", "mean max Q (reward units)"))  # fmt: skip
    for ax, (title, ylabel) in zip(axes, panels, strict=True):
        ax.set(xlabel="episode", ylabel=ylabel, title=title)
    axes[0].legend()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def session_figure(recording: Path, path: Path) -> Path:
    """The paper's semi-virtual figure from a recorded session: the pressure above the
    per-axis end-effector error (its first episode)."""
    from dammrl.stack.recording import session_traces
    from dammrl.views.plots import plot_session
    from dammrl_core.task import TaskSettings

    traces = session_traces(recording, None)
    title = f"{recording.name}: {len(traces.decisions)} decisions, {len(traces.pressure)} samples"
    return plot_session(traces, TaskSettings().goal_tolerance_m, title, path)


def _smooth(values: np.ndarray, window: int = 50) -> np.ndarray:
    finite = np.where(np.isfinite(values), values, np.nan)
    out = np.full_like(finite, np.nan)
    for k in range(len(finite)):
        chunk = finite[max(0, k - window + 1) : k + 1]
        if np.any(np.isfinite(chunk)):
            out[k] = np.nanmean(chunk)
    return out
