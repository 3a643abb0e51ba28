"""Training settings: reward weights and DQN hyper-parameters (environment ``DAMMRL_RL_``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.settings import FINITE, Settings


class RewardWeights(BaseModel):
    """r = alpha / (||e||^2 + 0.5) - beta t_step - gamma E_effort - eta N_osc + rho R_success.

    ``e`` is measured in **centimetres**: 1/(e^2 + 0.5) falls from 2 at the goal to 0.67 at
    1 cm and 0.04 at 5 cm, so the accuracy term discriminates within the last few steps
    (in metres it would be ~2 everywhere). ``t_step`` is the decision-to-decision time [s],
    ``E_effort`` the mechanical work sum |tau . dq| dt over the step [J], ``N_osc`` the
    waypoint reversals during the step, ``R_success`` 1 when the reach succeeds.
    """

    model_config = FINITE

    alpha: float = Field(1.0, ge=0)
    beta: float = Field(1.0, ge=0)
    gamma: float = Field(0.05, ge=0)
    eta: float = Field(0.1, ge=0)
    rho: float = Field(10.0, ge=0)

    @classmethod
    def preset(cls, reward: Literal[1, 2]) -> RewardWeights:
        """Reward 1 (accuracy focus): beta = 0. Reward 2: every term."""
        return cls(beta=0.0) if reward == 1 else cls()


class TrainSettings(Settings):
    """DQN hyper-parameters shared by both agents."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_RL_")

    episodes: int = Field(1500, ge=1, lt=100_000)
    """Training episodes."""
    max_decisions: int = Field(150, ge=1, le=10_000)
    """Decisions per episode before it is truncated."""
    gamma: float = Field(0.97, gt=0, le=1)
    """Discount per decision."""
    learning_rate: float = Field(5e-4, gt=0, le=1)
    """Adam's step size."""
    batch_size: int = Field(64, ge=1, le=65_536)
    """Transitions per gradient step."""
    buffer_size: int = Field(50_000, ge=100, le=100_000_000)
    """Transitions the replay buffer keeps."""
    learning_starts: int = Field(500, ge=0, le=100_000_000)
    """Transitions collected before the first update."""
    train_every: int = Field(1, ge=1, le=10_000)
    """Decisions between gradient steps."""
    target_update_every: int = Field(250, ge=1, le=10_000_000)
    """Gradient steps between target-network copies."""
    epsilon_start: float = Field(1.0, ge=0, le=1)
    """Exploration at the start: the share of random actions..."""
    epsilon_end: float = Field(0.05, ge=0, le=1)
    """... and after ``epsilon_decay_decisions``."""
    epsilon_decay_decisions: int = Field(15_000, ge=1, le=1_000_000_000)
    """Decisions over which epsilon falls linearly from start to end."""
    hidden: int = Field(128, ge=8, le=4096)
    """Units per hidden layer."""
    grad_clip: float = Field(10.0, gt=0, le=1000)
    """Gradients are clipped to this norm."""
    seed: int = Field(0, ge=0, lt=70)
    """The training run's seed (its task seeds are seed x 100,000 + episode, all below the
    held-out 7,000,000)."""
    randomize: bool = True
    """Train on randomised arms (the paper's S1): masses, damping, friction, link lengths,
    encoder offsets and sensor noise drawn anew every episode."""
