"""The simulated human (Agent_0): binary commands on the primary axis, with errors.

Pure: it perceives the end-effector position and the goal when asked, and answers with a
decision and how long that decision took. The caller (in-process runner or intent node)
makes the decision available only after that time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic_settings import SettingsConfigDict

from dammrl_core.human import HumanModel, direction_to_goal
from dammrl_core.intent.source import Ask, Decided, Reading, SourceContext
from dammrl_core.models import ModelSet
from dammrl_core.settings import Settings
from dammrl_core.state import Intent
from dammrl_core.task import seed_streams


@dataclass(frozen=True)
class Decision:
    intent: Intent  # t_s of the intent is when the decision becomes available
    correct: bool  # whether u_h points toward the goal (known only in simulation)
    decision_s: float  # how long the human took [s]


class SimulatedHuman:
    """Samples decisions from the human model (accuracy and decision time per radius)."""

    def __init__(
        self,
        human: HumanModel,
        models: ModelSet,
        seed: int | np.random.Generator | None = None,
    ) -> None:
        self.human = human
        self.models = models
        self.rng = np.random.default_rng(seed)  # a Generator passes through unchanged

    def decide(
        self, t_s: float, ee_pos: np.ndarray, goal: np.ndarray, axis: int, human_model: int
    ) -> Decision:
        """Decide at ``t_s`` from the perceived error along the primary ``axis``."""
        toward_goal = direction_to_goal(ee_pos, goal, axis)
        correct, decision_s = self.human.sample(self.rng, human_model)
        intent = Intent(
            t_s=t_s + decision_s,
            u_h=toward_goal if correct else -toward_goal,
            radius_m=self.models.radius_m(human_model),
            human_model=human_model,
        )
        return Decision(intent, correct, decision_s)


# ---- as an intent source (virtual mode) ------------------------------------------------
class SimulatedSettings(Settings):
    """The simulated human has no settings of its own: it is the stack's one
    ``DAMMRL_HUMAN_*`` (:class:`dammrl_core.human.HumanModel`)."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_SIMULATED_")


class SimulatedSource:
    """The simulated human answering each request at once, with the decision time it
    took: the controller applies it when its robot clock reaches the request time plus
    that time, as the in-process runner does (timed by the robot clock, not the bus).
    Reseeded with each episode's seed, so a seed draws the same decisions as in-process.
    A person who tires or learns (``DAMMRL_HUMAN_PERSON__FATIGUE_PER_REACH``, ...) is, in
    episode n of a run, the person after n - 1 reaches of one session."""

    person = False
    waits_for_model_choice = True  # it decides with the policy's radius

    def __init__(self, context: SourceContext) -> None:
        self.model = context.human
        self.human = SimulatedHuman(context.human, context.models)
        self.decided: Decided | None = None

    def open(self) -> None: ...

    def close(self) -> None: ...

    def new_episode(self, episode: int, seed: int) -> None:
        self.human.rng = seed_streams(seed).human
        self.human.human = self.model.practised(1, max(0, episode - 1))

    def ask(self, ask: Ask, now_s: float) -> None:
        decision = self.human.decide(ask.t_s, ask.ee_pos_m, ask.goal_m, ask.primary_axis,
                                     ask.human_model)  # fmt: skip
        self.decided = Decided(decision.intent.u_h, ask.human_model, 1.0, decision.decision_s,
                               decision.correct)  # fmt: skip

    def cancel(self) -> None:
        self.decided = None

    def poll(self, now_s: float) -> Decided | None:
        decided, self.decided = self.decided, None
        return decided

    def readings(self) -> list[Reading]:
        return []

    def problem(self) -> str | None:
        return None

    def detail(self) -> str:
        return ""


class SimulatedPlugin:
    name = "simulated"
    settings = SimulatedSettings

    def create(self, settings: Settings, context: SourceContext) -> SimulatedSource:
        return SimulatedSource(context)


PLUGIN = SimulatedPlugin()
