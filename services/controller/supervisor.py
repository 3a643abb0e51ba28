"""The episode supervisor of the bus stack: goals, success, metrics.

It draws each episode's start and goal exactly as the in-process runner does for the
same seed, logs the RobotStates the controller receives, decides when the reach is over
(goal held for the dwell time, timeout) and computes the metrics with the same function.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dammrl.errors import IKError
from dammrl.metrics import GoalMonitor, ReachMetrics, reach_metrics
from dammrl.state import RobotState, StepEvent
from dammrl.task import ReachTask, TaskSettings, task_for_seed
from services.controller.ik import DampedLeastSquaresIK


@dataclass
class Episode:
    number: int
    seed: int
    task: ReachTask
    q_start: np.ndarray
    goal_monitor: GoalMonitor
    samples: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)
    steps: list[StepEvent] = field(default_factory=list)
    decisions: list[bool] = field(default_factory=list)
    button_pressed: bool = False

    def record(self, state: RobotState) -> None:
        self.samples.append((state.t_s, state.ee_pos.copy(), state.ee_vel.copy()))
        self.button_pressed |= state.button_pressed

    def metrics(self, outcome: str, reason: str) -> ReachMetrics:
        t = np.array([s[0] for s in self.samples])
        x = np.array([s[1] for s in self.samples]).reshape(-1, 3)
        v = np.array([s[2] for s in self.samples]).reshape(-1, 3)
        return reach_metrics(
            outcome=outcome,
            reason=reason,
            t_end_s=float(t[-1]) if len(t) else 0.0,
            t=t,
            x=x if len(x) else self.task.start[None, :],
            v=v,
            goal=self.task.goal,
            subgoals=np.array([s.subgoal for s in self.steps]),
            radii=np.array([s.radius_m for s in self.steps]),
            decisions_correct=self.decisions,
            button_pressed=self.button_pressed,
        )


class Supervisor:
    def __init__(self, settings: TaskSettings, start_ik: DampedLeastSquaresIK, goal_z_m: float):
        self.settings = settings
        self.start_ik = start_ik
        self.goal_z_m = goal_z_m

    def episode(self, number: int) -> Episode:
        """Episode ``number`` (1-based): seed, start, goal and start posture."""
        seed = self.settings.seed + number - 1
        task = task_for_seed(self.settings, self.goal_z_m, seed)
        result = self.start_ik.solve(task.start, np.array(self.settings.home_q_rad))
        if result.error_m > 1e-4:
            raise IKError(f"start position {task.start.round(3).tolist()} m is not reachable")
        monitor = GoalMonitor(task.goal, self.settings.goal_tolerance_m, self.settings.goal_dwell_s)
        return Episode(number, seed, task, result.q, monitor)

    def finished(self, episode: Episode, state: RobotState) -> tuple[str, str] | None:
        """(outcome, reason) once the reach is over, else None."""
        if episode.goal_monitor.update(state.t_s, state.ee_pos):
            return "success", "goal reached"
        if state.t_s >= self.settings.episode_timeout_s:
            return "timeout", "episode timeout"
        return None
