"""The reach as a Gymnasium-style environment: one step per human decision (event trigger).

Observation: the policy's (``dammrl_core.policy.learned.observe``). Action (i, j) as
0-based indices: Agent_0 picks the admission radius i, Agent_1 the step vector j. The
reward of a step is the composite reward over the stretch until the next decision.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass
from typing import Any

import numpy as np

from dammrl.learning.rl.config import RewardWeights
from dammrl.stack.runner import Episode, ReachRunner
from dammrl_core.human import HumanModel
from dammrl_core.metrics import mechanical_work_j, n_oscillations
from dammrl_core.policy import ModelChoice, model_choice
from dammrl_core.policy.learned import ACTIONS, OBSERVATION_SIZE, observe
from dammrl_core.state import RobotState

__all__ = ["ACTIONS", "OBSERVATION_SIZE", "ReachEnv", "RewardTerms", "accuracy_term"]


@dataclass(frozen=True)
class RewardTerms:
    accuracy: float
    time_s: float
    effort_j: float
    oscillations: int
    success: bool

    def total(self, w: RewardWeights) -> float:
        return (
            w.alpha * self.accuracy
            - w.beta * self.time_s
            - w.gamma * self.effort_j
            - w.eta * self.oscillations
            + w.rho * float(self.success)
        )


def accuracy_term(error_m: float) -> float:
    """1 / (||e||^2 + 0.5) with e in centimetres."""
    return 1.0 / ((error_m * 100.0) ** 2 + 0.5)


class ReachEnv:
    """``reset(seed) -> (obs, info)``, ``step((i, j)) -> (obs, r, terminated, truncated, info)``."""

    def __init__(self, runner: ReachRunner, weights: RewardWeights, max_decisions: int) -> None:
        self.runner = runner
        self.weights = weights
        self.max_decisions = max_decisions
        self.models = runner.settings.models
        self.episode: Episode
        self._loop: Generator[RobotState, ModelChoice, None]
        self._state: RobotState
        self._mark = 0  # log row at the last decision
        self._decisions = 0
        self._model: tuple[int, int] | None = None

    def reset(
        self, seed: int, human: HumanModel | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """A new episode of ``seed`` (``human``: its simulated person, default the runner's)."""
        self.episode = self.runner.episode(seed, human=human)
        self._loop = self.episode.loop()
        self._state = next(self._loop)
        self._mark, self._decisions, self._model = 0, 0, None
        return self._observation(), {}

    def step(self, action: tuple[int, int]) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        i, j = int(action[0]) + 1, int(action[1]) + 1
        self._model = (i, j)
        choice = model_choice(self.models, i, j)
        self._decisions += 1
        try:
            self._state = self._loop.send(choice)
            terminated = False
        except StopIteration:
            terminated = True
            self._state = self.episode.last_state
        terms = self._terms(terminated)
        truncated = not terminated and self._decisions >= self.max_decisions
        info: dict[str, Any] = {"terms": terms, "model": (i, j)}
        if terminated or truncated:
            info["metrics"] = self.episode.result()[0]
        return self._observation(), terms.total(self.weights), terminated, truncated, info

    def _observation(self) -> np.ndarray:
        return observe(self._state.ee_pos, self.episode.task.goal, self._model)

    def _terms(self, terminated: bool) -> RewardTerms:
        episode = self.episode
        segment = episode.segment(self._mark)
        self._mark = episode.n
        effort, oscillations = 0.0, 0
        if len(segment.t) > 2:
            dt = episode.runner.control_dt_s
            effort = mechanical_work_j(segment.q, segment.tau, dt)
            oscillations = n_oscillations(
                segment.x,
                np.array([s.subgoal for s in episode.steps]).reshape(-1, 3),
                np.array([s.radius_m for s in episode.steps]),
                1.0 / dt,
            )
        error = float(np.linalg.norm(self._state.ee_pos - episode.task.goal))
        return RewardTerms(
            accuracy=accuracy_term(error),
            time_s=float(segment.t[-1] - segment.t[0]) if len(segment.t) else 0.0,
            effort_j=effort,
            oscillations=oscillations,
            success=terminated and episode.outcome == "success",
        )
