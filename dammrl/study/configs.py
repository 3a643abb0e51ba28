"""The configurations a study compares: the paper's four and the rows a reviewer asks for.

The paper's comparison (section "Comparison Study"):

1. fixed-frequency micro-steps with a fixed model, by the paper's mechanism: every timer
   tick plans a step from the previous subgoal, even while the last IK solve is still
   running (the "premature IK update" the paper blames for chatter), with the human's
   latest decision;
2. event-triggered progression with the same fixed model;
3. event-triggered DAMMRL trained with Reward 1 (accuracy);
4. event-triggered DAMMRL trained with Reward 2 (speed and accuracy).

Beside them: the fixed-frequency baseline made fair one choice at a time (a tick waits
for a pending solve and steps from the measured position; a fresh human decision per
step), the best fixed model under each progression (searched over all 16 M_ij on tuning
seeds disjoint from the evaluation seeds), and a uniformly random choice of (i, j) at
every decision. Which rows differ shows which modelling choice decides each claim.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from dammrl_core.policy.settings import SHIPPED_POLICY

PAPER_MODEL = (2, 1)  # the fixed model of configurations 1 and 2: E_small, all-small steps
SHIPPED = {1: SHIPPED_POLICY.parent.parent / "reward1", 2: SHIPPED_POLICY.parent}

# the paper's fixed-frequency mechanism, and each choice that makes it fair
PAPER_FIXED = {"fixed_step_from": "subgoal", "fixed_replan_while_pending": True,
               "fixed_decisions": "latest"}  # fmt: skip
FAIR_TIMING = {"fixed_step_from": "measured", "fixed_replan_while_pending": False,
               "fixed_decisions": "latest"}  # fmt: skip
FAIR_ALL = {**FAIR_TIMING, "fixed_decisions": "fresh"}

Role = Literal["paper", "variant", "reviewer"]


@dataclass(frozen=True)
class PolicySpec:
    """Who chooses M_ij: a fixed model, trained checkpoints (several runs aggregate:
    reach k of a run set uses run k mod n), or a uniformly random choice."""

    kind: Literal["fixed", "learned", "random", "adaptive"]
    model: tuple[int, int] = PAPER_MODEL
    checkpoints: tuple[Path, ...] = ()

    def text(self) -> str:
        if self.kind == "fixed":
            return f"M_{self.model[0]},{self.model[1]}"
        if self.kind == "random":
            return "uniform random (i, j)"
        if self.kind == "adaptive":
            return "adaptive around " + ", ".join(_short(p) for p in self.checkpoints[:1])
        return ", ".join(_short(p) for p in self.checkpoints)


def _short(path: Path) -> str:
    return path.parent.name if path.name == "checkpoint.pt" else path.name


@dataclass(frozen=True)
class Configuration:
    key: str  # short id used in tables and file names
    label: str
    role: Role
    trigger: Literal["event", "fixed"]
    policy: PolicySpec
    controller: dict[str, Any] = field(default_factory=dict)  # ControllerSettings overrides

    def with_model(self, model: tuple[int, int]) -> Configuration:
        return Configuration(
            self.key, f"{self.label} M_{model[0]},{model[1]}", self.role, self.trigger,
            PolicySpec("fixed", model), self.controller,
        )  # fmt: skip


def checkpoint_file(path: Path) -> Path:
    """A run directory or a checkpoint file: the checkpoint file."""
    return path / "checkpoint.pt" if path.is_dir() else path


def checkpoint_files(path: Path) -> list[Path]:
    """A run, a checkpoint, or a folder of seeds (``seed-*/``, ``dammrl train --seeds``):
    every checkpoint it holds."""
    seeds = sorted(path.glob("seed-*/checkpoint.pt"), key=lambda p: int(p.parent.name[5:]))
    return (
        seeds
        if path.is_dir() and not (path / "checkpoint.pt").exists() and seeds
        else [checkpoint_file(path)]
    )


def paper_configurations(
    reward1: tuple[Path, ...] = (), reward2: tuple[Path, ...] = ()
) -> list[Configuration]:
    """The four configurations of the paper (shipped policies unless runs are given)."""
    r1 = tuple(c for p in reward1 for c in checkpoint_files(p)) or (checkpoint_file(SHIPPED[1]),)
    r2 = tuple(c for p in reward2 for c in checkpoint_files(p)) or (checkpoint_file(SHIPPED[2]),)
    fixed = PolicySpec("fixed", PAPER_MODEL)
    return [
        Configuration("1-fixed", "1 fixed-frequency (paper's mechanism)", "paper", "fixed",
                      fixed, PAPER_FIXED),
        Configuration("2-event", "2 event-triggered, fixed model", "paper", "event", fixed),
        Configuration("3-dammrl-r1", "3 DAMMRL, Reward 1", "paper", "event",
                      PolicySpec("learned", checkpoints=r1)),
        Configuration("4-dammrl-r2", "4 DAMMRL, Reward 2", "paper", "event",
                      PolicySpec("learned", checkpoints=r2)),
    ]  # fmt: skip


def variant_configurations() -> list[Configuration]:
    """The fixed-frequency baseline made fair, one modelling choice at a time."""
    fixed = PolicySpec("fixed", PAPER_MODEL)
    return [
        Configuration("1b-fixed-timing", "1b fixed-frequency, waits for IK, steps from measured",
                      "variant", "fixed", fixed, FAIR_TIMING),
        Configuration("1c-fixed-fresh", "1c fixed-frequency, fair timing + fresh decision/step",
                      "variant", "fixed", fixed, FAIR_ALL),
    ]  # fmt: skip


def adaptive_configuration(reward2: tuple[Path, ...] = ()) -> Configuration:
    """Configuration 4 inside the adaptive mode (``dammrl study --adaptive``): the seeds as
    one session per randomisation setting, in order, the posterior over M_ij carried
    from reach to reach and the targets of ``DAMMRL_POLICY_TARGETS__*``."""
    runs = tuple(c for p in reward2 for c in checkpoint_files(p))
    r2 = runs or (checkpoint_file(SHIPPED[2]),)
    label = "4a DAMMRL, Reward 2, adaptive (S3 re-selection)"
    policy = PolicySpec("adaptive", checkpoints=r2[:1])
    return Configuration("4a-adaptive-r2", label, "variant", "event", policy)


def reviewer_configurations() -> list[Configuration]:
    """The random-choice row; the best-fixed rows are made once the search has run."""
    return [
        Configuration("random", "event-triggered, uniformly random (i, j)", "reviewer", "event",
                      PolicySpec("random")),
    ]  # fmt: skip


def best_fixed_candidates() -> list[Configuration]:
    """Every M_ij under each progression (fixed-frequency by the paper's mechanism)."""
    bases = (
        Configuration("best-fixed", "best fixed model, fixed-frequency", "reviewer", "fixed",
                      PolicySpec("fixed"), PAPER_FIXED),
        Configuration("best-event", "best fixed model, event-triggered", "reviewer", "event",
                      PolicySpec("fixed")),
    )  # fmt: skip
    return [base.with_model((i, j)) for base in bases for i in (1, 2) for j in range(1, 9)]
