"""The model table: what every option gives a simulated person of any accuracy, so the
posterior over M_ij can predict every option for *this* person.

Each option (the 16 M_ij and the base policy, the shipped DQN) was run in simulation on a
grid of persons (``dammrl coadapt table``): for M_ij the person's accuracy under radius i
on a grid of nodes; for the base policy, which uses both radii, on a grid of both
accuracies. The same task seeds at every node (common random numbers), a simulated
timeout far past the task's (``simulated_timeout_s``), and the sub-models' decision times.
Every reach is kept, with how its time splits:

    t = other + d_big + d_small + execution

(the decision times under each radius, and the steps' execution times). A person who
decides r_i times slower than the sub-model under radius i, on an arm whose steps take s
times the nominal arm's, would have taken

    t' = t + (r_big - 1) d_big + (r_small - 1) d_small + (s - 1) execution

and succeeds when the simulated reach succeeded and t' is within the task's horizon
(``horizon_s``). Scaling the decision times leaves every draw of the reach as it was (the
simulated person draws a decision's correctness and its time from separate numbers), so
this is the reach that person would have made, bar the arm settling a little longer or
shorter between steps. Between nodes the prediction is interpolated linearly (bilinearly
for the base policy). ``predict`` does this for many persons at once (draws from the
posterior of the person): per option, each draw's success probability and mean log time.
"""

from __future__ import annotations

import functools
import gzip
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

from dammrl_core.errors import ConfigurationError
from dammrl_core.models import HUMAN_MODELS, ROBOT_MODELS

Option = tuple[int, ...]
"""(i, j): M_ij; (0, 0): the base policy; (i, j, k): the steps halfway between M_ij's and
M_ik's, j and k neighbours (their step vectors differ on one axis)."""
BASE: Option = (0, 0)
"""The base policy itself (the learned DQN, choosing M_ij per state): an option beside
the 16 models, with beliefs of its own. Its reaches are credited to it, not to the M_ij
it chose most: a policy that changes j along a reach is faster than any fixed M_ij, and
crediting its reaches to one would make that model look better than it is."""
MODELS: tuple[Option, ...] = tuple((i, j) for i in HUMAN_MODELS for j in ROBOT_MODELS)
"""Every M_ij, in the posterior's order (i major)."""
OPTIONS: tuple[Option, ...] = (BASE, *MODELS)
MIDPOINTS: tuple[Option, ...] = tuple(
    (i, j, k)
    for i in HUMAN_MODELS
    for j in ROBOT_MODELS
    for k in ROBOT_MODELS
    if j < k and bin((j - 1) ^ (k - 1)).count("1") == 1
)
"""The bounded online interpolation's options: each radius, halfway between two
neighbouring step vectors (one axis halfway between its small and large step): 24."""
TABLE = Path(str(resources.files("dammrl_core").joinpath("policies", "model_table.json.gz")))
COLUMNS = ("success", "t_s", "decide_big_s", "decide_small_s", "execute_s", "log_error",
           "sparc", "scale_x", "scale_y", "scale_z")  # fmt: skip
"""What the table keeps of each reach: success within the simulated timeout, its time
[s], its time deciding under E_big and E_small [s], executing steps [s], log final error
[log m], SPARC, and the mean step scale per axis (0: every step small, 1: every step
large)."""
Radius = Literal["big", "small"]


class OptionReaches(BaseModel):
    """One option's reaches on its grid of persons."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=True)

    human_model: int = Field(ge=0, le=2)  # (0, 0): the base policy
    robot_model: int = Field(ge=0, le=8)
    axes: tuple[Radius, ...]
    """Which accuracies vary over the grid: ('big',) for M_1j, ('small',) for M_2j, both
    for the base policy."""
    grid: tuple[tuple[float, ...], ...]
    """The accuracy nodes of each axis (increasing)."""
    columns: dict[str, list[list[float]]]
    """COLUMNS -> one list per node (row-major over ``axes``), one value per seed."""
    _arrays: dict[str, np.ndarray] = PrivateAttr(default_factory=dict)

    @model_validator(mode="after")
    def _shape(self) -> OptionReaches:
        nodes = math.prod(len(g) for g in self.grid)
        if len(self.axes) != len(self.grid) or any(len(g) < 2 for g in self.grid):
            raise ValueError("one grid of two or more nodes per axis")
        if set(self.columns) != set(COLUMNS):
            raise ValueError(f"columns must be {COLUMNS}")
        sizes = {len(seeds) for c in self.columns.values() for seeds in c}
        if any(len(c) != nodes for c in self.columns.values()) or len(sizes) != 1:
            raise ValueError("one list per node, the same number of seeds in each")
        return self

    @property
    def option(self) -> Option:
        return (self.human_model, self.robot_model)

    def array(self, column: str) -> np.ndarray:
        """(nodes, seeds), made once (the model is frozen)."""
        if column not in self._arrays:
            self._arrays[column] = np.asarray(self.columns[column], dtype=float)
        return self._arrays[column]


@dataclass(frozen=True)
class Persons:
    """Persons to predict for, one per draw (arrays of one shape, (K,))."""

    accuracy_big: np.ndarray
    accuracy_small: np.ndarray
    time_ratio_big: np.ndarray  # the person's decision times over the sub-model's
    time_ratio_small: np.ndarray
    arm_scale: np.ndarray  # the arm's step times over the nominal arm's

    @classmethod
    def one(cls, a_big: float, a_small: float, r_big: float = 1.0, r_small: float = 1.0,
            s: float = 1.0) -> Persons:  # fmt: skip
        return cls(*(np.array([v], dtype=float) for v in (a_big, a_small, r_big, r_small, s)))


@dataclass(frozen=True)
class Prediction:
    """What an option gives each person of a ``Persons`` (arrays (K,))."""

    success: np.ndarray  # probability of success within the horizon
    log_time: np.ndarray  # mean log reach time [log s] (a failed reach: its end, at most
    # the horizon)
    log_time_sd: float  # sd of one reach's log time around that mean
    log_time_success: np.ndarray  # mean log time of the successes [log s] (none: the horizon)
    to_success_s: np.ndarray  # mean time to success, a failure counting the horizon [s]
    log_error: float  # mean log final error [log m]
    log_error_sd: float
    sparc: float
    sparc_sd: float
    scale: np.ndarray  # mean step scale per axis (3,), 0 small to 1 large


class ModelTable(BaseModel):
    """Every option's simulated reaches on a grid of persons, and the nominal arm's step
    time, log tau = c + b_L log L + b_eps log eps (a step of length L to within an
    admission radius eps), with its log-sd."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    seeds: str
    horizon_s: float = Field(gt=0)
    """The task's episode limit: a reach succeeds within it."""
    simulated_timeout_s: float = Field(gt=0)
    """The simulated reaches' limit (past the horizon, for persons quicker than the model)."""
    step_time_log_intercept: float
    step_time_log_length: float
    step_time_log_radius: float
    step_time_log_sd: float = Field(gt=0)
    options: tuple[OptionReaches, ...]

    def reaches(self, option: Option) -> OptionReaches:
        for reaches in self.options:
            if reaches.option == option:
                return reaches
        raise ConfigurationError(f"the model table has no option {option}")

    def step_time_s(self, length_m: float, radius_m: float) -> float:
        """The nominal arm's execution time of a step [s]."""
        log_tau = (self.step_time_log_intercept
                   + self.step_time_log_length * math.log(max(length_m, 1e-4))
                   + self.step_time_log_radius * math.log(max(radius_m, 1e-4)))  # fmt: skip
        return math.exp(log_tau)

    def predict(self, option: Option, persons: Persons) -> Prediction:
        """The option's success and mean log time for each person (see the module); a
        midpoint's, the mean of its two neighbours' (an assumption its own reaches correct)."""
        if len(option) == 3:
            i, j, k = option
            return halfway(self.predict((i, j), persons), self.predict((i, k), persons))
        reaches = self.reaches(option)
        nodes, weights = _corners(reaches, persons)  # (K, corners) each

        def at(column: str) -> np.ndarray:  # (K, corners, seeds)
            return np.asarray(reaches.array(column)[nodes])

        extra = ((persons.time_ratio_big - 1)[:, None, None] * at("decide_big_s")
                 + (persons.time_ratio_small - 1)[:, None, None] * at("decide_small_s")
                 + (persons.arm_scale - 1)[:, None, None] * at("execute_s"))  # fmt: skip
        scaled = np.maximum(at("t_s") + extra, 1e-3)
        success = (at("success") > 0.5) & (scaled <= self.horizon_s)
        log_time = np.log(np.minimum(scaled, self.horizon_s))
        to_success = np.where(success, scaled, self.horizon_s)
        successes = success.sum(axis=2)
        log_success = np.where(
            successes > 0,
            np.where(success, log_time, 0.0).sum(axis=2) / np.maximum(successes, 1),
            math.log(self.horizon_s),
        )
        log_error, sparc = reaches.array("log_error"), reaches.array("sparc")
        scale = np.array([reaches.array(f"scale_{a}").mean() for a in "xyz"])
        return Prediction(
            success=(weights * success.mean(axis=2)).sum(axis=1),
            log_time=(weights * log_time.mean(axis=2)).sum(axis=1),
            log_time_sd=max(float(np.sqrt(np.mean(log_time.var(axis=2)))), 0.05),
            log_time_success=(weights * log_success).sum(axis=1),
            to_success_s=(weights * to_success.mean(axis=2)).sum(axis=1),
            log_error=float(log_error.mean()),
            log_error_sd=max(float(log_error.std()), 0.05),
            sparc=float(np.nanmean(sparc)),
            sparc_sd=max(float(np.nanstd(sparc)), 0.1),
            scale=scale,
        )

    def dumps(self) -> bytes:
        return gzip.compress(self.model_dump_json().encode(), mtime=0)

    @classmethod
    def load(cls, path: Path = TABLE) -> ModelTable:
        """The table at ``path`` (read once per process: it is frozen)."""
        return _load(path)

    @classmethod
    def read(cls, path: Path) -> ModelTable:
        try:
            table = cls.model_validate(json.loads(gzip.decompress(path.read_bytes())))
        except (OSError, EOFError, ValueError) as exc:
            raise ConfigurationError(f"model table {path}: {' '.join(str(exc).split())[:300]}"
                                     ) from exc  # fmt: skip
        if sorted(r.option for r in table.options) != sorted(OPTIONS):
            raise ConfigurationError(
                f"model table {path} must have one entry per M_ij and the base policy's"
            )
        return table


def halfway(a: Prediction, b: Prediction) -> Prediction:
    """A midpoint option's prediction: the mean of its neighbours' (an assumption)."""
    return Prediction(
        success=(a.success + b.success) / 2,
        log_time=(a.log_time + b.log_time) / 2,
        log_time_sd=(a.log_time_sd + b.log_time_sd) / 2,
        log_time_success=(a.log_time_success + b.log_time_success) / 2,
        to_success_s=(a.to_success_s + b.to_success_s) / 2,
        log_error=(a.log_error + b.log_error) / 2,
        log_error_sd=(a.log_error_sd + b.log_error_sd) / 2,
        sparc=(a.sparc + b.sparc) / 2,
        sparc_sd=(a.sparc_sd + b.sparc_sd) / 2,
        scale=(a.scale + b.scale) / 2,
    )


@functools.lru_cache(maxsize=4)
def _load(path: Path) -> ModelTable:
    return ModelTable.read(path)


def _corners(reaches: OptionReaches, persons: Persons) -> tuple[np.ndarray, np.ndarray]:
    """Each person's interpolation nodes and weights, (K, 2^axes) each: linear per axis
    (clipped to the grid's ends), nodes row-major (the first axis varies slowest)."""
    nodes = np.zeros((len(persons.accuracy_big), 1), dtype=int)
    weights = np.ones((len(persons.accuracy_big), 1))
    for axis, grid in zip(reaches.axes, reaches.grid, strict=True):
        values = persons.accuracy_big if axis == "big" else persons.accuracy_small
        lower, frac = _bracket(np.asarray(grid), values)
        nodes = np.concatenate([nodes * len(grid) + lower[:, None],
                                nodes * len(grid) + lower[:, None] + 1], axis=1)  # fmt: skip
        weights = np.concatenate([weights * (1 - frac)[:, None], weights * frac[:, None]], axis=1)
    return nodes, weights


def _bracket(grid: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The node below each value (K,) on ``grid`` and the fraction of the way to the next."""
    x = np.clip(values, grid[0], grid[-1])
    lower = np.clip(np.searchsorted(grid, x, side="right") - 1, 0, len(grid) - 2)
    return lower, (x - grid[lower]) / (grid[lower + 1] - grid[lower])


def option_name(option: Option) -> str:
    if option == BASE:
        return "the base policy"
    if len(option) == 3:
        return f"M_{option[0]},{option[1]}|{option[2]} (halfway)"
    return f"M_{option[0]},{option[1]}"


def grid_persons(axes: Sequence[Radius], grid: Sequence[Sequence[float]]
                 ) -> list[tuple[float | None, float | None]]:  # fmt: skip
    """The (accuracy_big, accuracy_small) of each node, row-major (None: the sub-model's)."""
    nodes: list[tuple[float | None, float | None]] = [(None, None)]
    for axis, values in zip(axes, grid, strict=True):
        nodes = [
            (v if axis == "big" else big, v if axis == "small" else small)
            for big, small in nodes
            for v in values
        ]
    return nodes
