"""The reaching task: start and goal sampling, goal tolerance, time limits.

Defaults describe a seated button-press reach with the shoulder at the origin of the
task frame (x forward, y left, z up), the table 0.25 m below it: the hand starts 15-25 cm
above the table near the body and reaches 0.2-0.4 m forward and down onto a button
(cap radius 3 cm) somewhere on the table in front of it. The goal point is the fingertip
centre pressing the button cap 8 mm down (it registers a press at 3 mm; see
``SceneLayout.goal_press_depth_m``). Success is the button pressed and held for
``goal_dwell_s``; the paper's criterion, ||x - x_g|| <= eps_g, is reported beside it as
``reached``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Self

import numpy as np
from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from dammrl_core.dynamics import ArmModel
from dammrl_core.errors import ConfigurationError, IKError
from dammrl_core.ik import DampedLeastSquaresIK
from dammrl_core.robot.scene import SceneLayout
from dammrl_core.settings import PerJoint, Settings, ordered

START_ACCEPT_ERROR_M = 1e-4  # a start posture farther than this from x_s is refused
HELD_OUT_START = 7_000_000
"""Task seeds from here on are held out: no training episode ever draws one; evaluation,
sweeps and studies do (``held_out_seeds``), so every tool reports on the same unseen set."""
TRAINING_SEEDS_PER_RUN = 100_000
"""Training run ``s`` draws the task seeds s * 100 000 + episode (``training_seed``)."""
MAX_SEED = 2**32 - 1
# positions in the task frame: in front of the shoulder, within the arm's reach (0.74 m)
_X = Annotated[float, Field(ge=0.05, le=0.8)]
_Y = Annotated[float, Field(ge=-0.8, le=0.8)]
_Z = Annotated[float, Field(ge=-0.8, le=0.8)]
_Distance = Annotated[float, Field(gt=0, le=0.8)]


class TaskSettings(Settings):
    """Environment prefix ``DAMMRL_TASK_``."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_TASK_")

    goal_tolerance_m: float = Field(0.042, gt=0, le=0.1)
    """eps_g: the paper's criterion ||x - x_g|| <= eps_g, reported as ``reached`` beside
    success (the button pressed). The cap radius (30 mm) plus the fingertip's (12 mm): the
    farthest the fingertip's centre can be from x_g while it touches the cap, so a press
    is always within eps_g [m]."""
    goal_dwell_s: float = Field(0.1, ge=0, le=10)
    """How long the button must stay pressed for success [s]."""
    episode_timeout_s: float = Field(60.0, ge=1, le=3600)
    """A reach still running after this long ends as a timeout [s] (1 s - 1 h)."""
    start_min_m: tuple[_X, _Y, _Z] = (0.28, -0.15, -0.10)
    """Lower corner of the box of start positions..."""
    start_max_m: tuple[_X, _Y, _Z] = (0.38, 0.15, 0.0)
    """Box of start positions x_s [m] (x 0.05-0.8, y and z -0.8-0.8; each minimum at most
    its maximum)."""
    goal_min_xy_m: tuple[_X, _Y] = (0.45, -0.15)
    """Lower corner of the box of button positions..."""
    goal_max_xy_m: tuple[_X, _Y] = (0.60, 0.15)
    """Box of button positions on the table [m]; the goal height follows the table."""
    reach_distance_m: tuple[_Distance, _Distance] = (0.2, 0.4)
    """Allowed ||x_g - x_s|| [m] (shortest, longest)."""
    table_top_z_m: float = Field(-0.25, ge=-0.8, le=0)
    """Table height in the robot base frame [m] (the shoulder is the origin; -0.8-0)."""
    home_q_rad: PerJoint = (0.0, 1.0, 0.0, 1.6, 0.0, 0.3)
    """Posture from which the start posture is solved [rad]."""
    start_limit_margin_rad: float = Field(0.02, ge=0, le=0.2)
    """The start posture stays this far inside the joint limits [rad]."""
    episodes: int | None = Field(None, ge=1, le=1_000_000)
    """Episodes the bus supervisor runs (None: until stopped)."""
    seed: int = Field(0, ge=0, le=MAX_SEED)
    """Seed of the first episode; episode k uses seed + k - 1 (same draws as `dammrl reach`)."""

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        """Boxes and the distance range whose minimum is not above their maximum."""
        ordered(self, "start_min_m", "start_max_m", strict=False)
        ordered(self, "goal_min_xy_m", "goal_max_xy_m", strict=False)
        shortest, longest = self.reach_distance_m
        if shortest > longest:
            raise ValueError(f"reach_distance_m[0]={shortest:g}: outside its range (0, "
                             f"{longest:g}] (the shortest reach, at most the longest, "
                             f"reach_distance_m[1]={longest:g})")  # fmt: skip
        return self


@dataclass(frozen=True)
class ReachTask:
    start: np.ndarray  # x_s (3,) [m]
    goal: np.ndarray  # x_g (3,) [m]


@dataclass(frozen=True)
class SeedStreams:
    """Independent random streams of one episode seed, one per consumer.

    Every composition (in-process or on the bus) draws each from its own stream, so one
    seed gives the same start, goal, human decisions, IK latencies and simulated arm
    wherever it runs.
    """

    task: np.random.Generator  # start and goal
    human: np.random.Generator  # the simulated human's decisions and decision times
    ik_latency: np.random.Generator  # the controller's IK latency model
    sim: np.random.Generator  # domain randomisation and sensor noise
    policy: np.random.Generator  # a randomised policy (the study's random-choice row)


def training_seed(run_seed: int, episode: int) -> int:
    """The task seed of a training episode; never a held-out one."""
    seed = run_seed * TRAINING_SEEDS_PER_RUN + episode
    if not 0 <= episode < TRAINING_SEEDS_PER_RUN or not 0 <= seed < HELD_OUT_START:
        raise ConfigurationError(
            f"training run {run_seed}, episode {episode} would use task seed {seed}: training "
            f"uses seeds below {HELD_OUT_START:,} (run seed <= "
            f"{HELD_OUT_START // TRAINING_SEEDS_PER_RUN - 1}, < {TRAINING_SEEDS_PER_RUN:,} "
            "episodes)"
        )
    return seed


def held_out_seeds(spec: str | int) -> range:
    """The evaluation seeds: ``N`` (the first N held-out seeds) or ``A:B`` (seeds A to B-1,
    all held out)."""
    text = str(spec).strip()
    try:
        if ":" in text:
            first, end = (int(part) for part in text.split(":", 1))
        else:
            first, end = HELD_OUT_START, HELD_OUT_START + int(text)
    except ValueError:
        raise ConfigurationError(f"seeds must be N or A:B, got {text!r}") from None
    if not HELD_OUT_START <= first < end:
        raise ConfigurationError(
            f"seeds {text!r}: need at least one seed, all >= {HELD_OUT_START:,} (held out "
            "from training)"
        )
    return range(first, end)


def seed_streams(seed: int) -> SeedStreams:
    """The named streams of episode ``seed`` (spawned in this order: keep it)."""
    task, human, ik_latency, sim, policy = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5)
    )
    return SeedStreams(task=task, human=human, ik_latency=ik_latency, sim=sim, policy=policy)


def scene_layout(settings: TaskSettings, timestep_s: float = 0.001) -> SceneLayout:
    """The table and button geometry of the task."""
    return SceneLayout(table_top_z_m=settings.table_top_z_m, timestep_s=timestep_s)


def task_for_seed(settings: TaskSettings, seed: int) -> ReachTask:
    """The start and goal of ``seed``."""
    return sample_task(settings, scene_layout(settings).goal_z_m, seed_streams(seed).task)


def start_posture(arm: ArmModel, settings: TaskSettings, start: np.ndarray) -> np.ndarray:
    """Joint positions [rad] (6,) placing the end-effector at ``start`` [m], solved from
    the home posture inside the joint limits (less ``start_limit_margin_rad``)."""
    ik = DampedLeastSquaresIK(arm, limit_margin_rad=settings.start_limit_margin_rad)
    result = ik.solve(np.asarray(start, dtype=float), np.array(settings.home_q_rad))
    if result.error_m > START_ACCEPT_ERROR_M:
        raise IKError(f"start position {np.round(start, 3).tolist()} m is not reachable")
    return result.q


def sample_task(settings: TaskSettings, goal_z_m: float, rng: np.random.Generator) -> ReachTask:
    """Uniform start and goal in their boxes, redrawn until the distance is in range."""
    lo, hi = settings.reach_distance_m
    for _ in range(1000):
        start = rng.uniform(settings.start_min_m, settings.start_max_m)
        goal = np.append(rng.uniform(settings.goal_min_xy_m, settings.goal_max_xy_m), goal_z_m)
        if lo <= np.linalg.norm(goal - start) <= hi:
            return ReachTask(start, goal)
    raise ConfigurationError(
        f"no start/goal pair {lo}-{hi} m apart in the configured boxes; widen them"
    )
