"""What a study runs: the configurations (the rows) and the conditions (arm and IK timing).

The paper's comparison (section "Comparison Study"):

1. fixed-frequency micro-steps with a fixed model, as the paper's text defines them: every
   timer tick plans x_{k+1} = x_k + dx from the current (measured) end-effector position
   x_k with the human's latest decision and solves its IK (one solve at a time: the text
   does not say that ticks overlap running solves);
2. event-triggered progression with the same fixed model;
3. event-triggered DAMMRL trained with Reward 1 (accuracy);
4. event-triggered DAMMRL trained with Reward 2 (speed and accuracy), and the same with the
   paper's dynamic layer (the resolved-acceleration feed-forward with its null-space term).

Configurations 3 and 4 use every training seed of their reward (reach k of the study runs
seed k mod n), so training-seed variation is inside the intervals. Beside them, each
labelled as ours: configuration 1 built other ways one choice at a time (chained from the
last subgoal, solves that overlap, a fresh decision per step), the shipped run of each
reward (the best seed on validation seeds), the best fixed model under each progression
(searched over all 16 M_ij on tuning seeds disjoint from the evaluation seeds) and a
uniformly random choice of (i, j). Which rows differ shows which modelling choice decides
each claim.

A condition is the arm and the IK timing every configuration runs on: the nominal or the
randomised arm with IK latency drawn from the ikpy-fitted lognormal, or the paper's solver
in the loop with each solve's own time entering simulated time. That time is the
reference machine's by default (``ikpy-real``: each solve's work, its forward-kinematics
evaluations, at the reference's measured cost per evaluation), so no verdict depends on
the computer that runs the study; ``ikpy-measured`` uses this computer's processor time
instead (an explicit choice, labelled with the machine in the report), and the
``ikpy-real-xS`` conditions scale the reference time by S: how the verdicts depend on
solve time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from dammrl_core.policy.settings import SHIPPED_POLICY

PAPER_MODEL = (2, 1)  # the fixed model of configurations 1 and 2: E_small, all-small steps
SHIPPED = {1: SHIPPED_POLICY.parent.parent / "reward1", 2: SHIPPED_POLICY.parent}
SEED_RUNS = {k: path / "seeds" for k, path in SHIPPED.items()}  # every training seed shipped

# configuration 1 by the paper's text, and each choice of ours that builds it another way
PAPER_FIXED = {"fixed_step_from": "measured", "fixed_replan_while_pending": False,
               "fixed_decisions": "latest"}  # fmt: skip
CHAINED = {**PAPER_FIXED, "fixed_step_from": "subgoal"}
OVERLAPPING = {**PAPER_FIXED, "fixed_replan_while_pending": True}
CHAINED_OVERLAPPING = {**CHAINED, "fixed_replan_while_pending": True}
FRESH = {**PAPER_FIXED, "fixed_decisions": "fresh"}
RESOLVED_ACCELERATION = {"feedforward": "resolved_acceleration"}

Role = Literal["paper", "ours", "reviewer"]
ROLE_TEXT = {"paper": "paper's", "ours": "ours", "reviewer": "reviewer's"}
FIXED, EVENT, R1, R2 = "1-fixed", "2-event", "3-dammrl-r1", "4-dammrl-r2"
PAPER_KEYS = (FIXED, EVENT, R1, R2)


@dataclass(frozen=True)
class PolicySpec:
    """Who chooses M_ij: a fixed model, trained checkpoints (several runs aggregate:
    reach k of a run set uses run k mod n), or a uniformly random choice."""

    kind: Literal["fixed", "learned", "random", "adaptive"]
    model: tuple[int, int] = PAPER_MODEL
    checkpoints: tuple[Path, ...] = ()

    @property
    def runs(self) -> int:
        """Training runs behind the policy (0: it learns nothing): the units its
        comparisons are judged over when several."""
        return len(self.checkpoints) if self.kind == "learned" else 0

    def text(self) -> str:
        if self.kind == "fixed":
            return f"M_{self.model[0]},{self.model[1]}"
        if self.kind == "random":
            return "uniform random (i, j)"
        if self.kind == "adaptive":
            return "adaptive around " + ", ".join(_short(p) for p in self.checkpoints[:1])
        if len(self.checkpoints) > 2:
            return f"{len(self.checkpoints)} training seeds of {_short(self.checkpoints[0], 2)}"
        return ", ".join(_short(p) for p in self.checkpoints)


def _short(path: Path, up: int = 1) -> str:
    """A checkpoint's run name (``up`` = 2: the run its seed belongs to)."""
    run = path.parent if path.name == "checkpoint.pt" else path
    if up == 2 and run.name.startswith("seed-"):
        group = run.parent  # runs/r2/seed-0, or a shipped policy's seeds/seed-0
        return group.parent.name if group.name == "seeds" else group.name
    return run.name


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


@dataclass(frozen=True)
class Condition:
    """The arm and the IK timing of a set of reaches."""

    key: str
    label: str
    randomize: bool  # domain randomisation: arm dynamics, kinematics, sensor noise
    controller: dict[str, Any] = field(default_factory=dict)  # ControllerSettings overrides
    randomization: dict[str, Any] = field(default_factory=dict)  # DomainRandomization overrides
    configurations: tuple[str, ...] | None = None  # the keys it runs (None: every row)

    @property
    def measured(self) -> bool:
        """Its IK latencies are measured on this computer (saved with the study, to be
        replayed: nothing else about a reach depends on where it ran)."""
        return self.controller.get("ik_latency") == "measured"

    @property
    def solves_timed(self) -> bool:
        """Each IK solve's own time enters simulated time (measured or the reference's)."""
        return self.controller.get("ik_latency") in ("measured", "reference")

    def runs(self, configuration: Configuration) -> bool:
        return self.configurations is None or configuration.key in self.configurations


IKPY_REAL = {"ik_solver": "ikpy", "ik_latency": "reference"}
LATENCY_SCALES = (0.25, 0.5, 2.0, 4.0)  # the reference machine's solve times times these
CONDITIONS = {
    c.key: c
    for c in (
        Condition("nominal", "nominal arm; IK latency drawn from the ikpy-fitted lognormal", False),
        Condition("randomised", "randomised arm and sensor noise; IK latency drawn", True),
        Condition("ikpy-real", "nominal arm; ikpy solves in the loop, each one's time on the "
                  "reference machine (its work at the reference's measured cost) in simulated "
                  "time", False, IKPY_REAL, {}, PAPER_KEYS),
        Condition("ikpy-measured", "nominal arm; ikpy solves in the loop, each one's processor "
                  "time on this computer in simulated time", False,
                  {"ik_solver": "ikpy", "ik_latency": "measured"}, {}, PAPER_KEYS),
        Condition("ikpy-drawn", "nominal arm; ikpy solves, latency drawn (not the solve's)",
                  False, {"ik_solver": "ikpy"}, {}, PAPER_KEYS),
        Condition("dls-real", "nominal arm; damped-least-squares solves, each one's time on the "
                  "reference machine (~0.2 ms)", False, {"ik_latency": "reference"}, {},
                  PAPER_KEYS),
        Condition("randomised-quiet-velocity", "randomised arm without end-effector velocity "
                  "noise", True, {}, {"ee_vel_noise_m_per_s": 0.0}, PAPER_KEYS),
        *(Condition(f"ikpy-real-x{scale:g}", f"as ikpy-real, every solve {scale:g} times as "
                    "long (a slower or faster computer)", False,
                    {**IKPY_REAL, "ik_latency_scale": scale}, {}, PAPER_KEYS)
          for scale in LATENCY_SCALES),
    )
}  # fmt: skip
DEFAULT_CONDITIONS = ("nominal", "randomised", "ikpy-real")


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


def _runs(given: tuple[Path, ...], reward: int) -> tuple[Path, ...]:
    """The checkpoints given, or every shipped training seed of ``reward``."""
    return tuple(c for p in given or (SEED_RUNS[reward],) for c in checkpoint_files(p))


def paper_configurations(
    reward1: tuple[Path, ...] = (), reward2: tuple[Path, ...] = ()
) -> list[Configuration]:
    """The paper's configurations (every shipped training seed unless runs are given)."""
    fixed = PolicySpec("fixed", PAPER_MODEL)
    r1, r2 = PolicySpec("learned", checkpoints=_runs(reward1, 1)), PolicySpec(
        "learned", checkpoints=_runs(reward2, 2))  # fmt: skip
    return [
        Configuration(FIXED, "1 fixed-frequency, x_k measured, one solve at a time", "paper",
                      "fixed", fixed, PAPER_FIXED),
        Configuration(EVENT, "2 event-triggered, fixed model", "paper", "event", fixed),
        Configuration(R1, "3 DAMMRL, Reward 1", "paper", "event", r1),
        Configuration(R2, "4 DAMMRL, Reward 2", "paper", "event", r2),
        Configuration("4ra-dammrl-r2", "4 with the resolved-acceleration feed-forward", "paper",
                      "event", r2, RESOLVED_ACCELERATION),
    ]  # fmt: skip


def variant_configurations() -> list[Configuration]:
    """Configuration 1 built other ways, one choice of ours at a time, and the shipped runs."""
    fixed = PolicySpec("fixed", PAPER_MODEL)
    shipped = {k: PolicySpec("learned", checkpoints=(checkpoint_file(SHIPPED[k]),))
               for k in SHIPPED}  # fmt: skip
    return [
        Configuration("1v-chained", "1, chained from the last subgoal", "ours", "fixed", fixed,
                      CHAINED),
        Configuration("1v-overlapping", "1, ticks plan while a solve runs (solves overlap)",
                      "ours", "fixed", fixed, OVERLAPPING),
        Configuration("1v-chained-overlapping", "1, chained and overlapping (claims v1's "
                      "configuration 1)", "ours", "fixed", fixed, CHAINED_OVERLAPPING),
        Configuration("1v-fresh", "1, a fresh decision per step", "ours", "fixed", fixed, FRESH),
        Configuration("3s-dammrl-r1", "3, the shipped run (best seed on validation)", "ours",
                      "event", shipped[1]),
        Configuration("4s-dammrl-r2", "4, the shipped run (best seed on validation)", "ours",
                      "event", shipped[2]),
    ]  # fmt: skip


def adaptive_configuration(reward2: tuple[Path, ...] = ()) -> Configuration:
    """Configuration 4 inside the adaptive mode (``dammrl study --adaptive``): each seed set
    as one session per arm (nominal, randomised), in order, the posterior over M_ij carried
    from reach to reach and the targets of ``DAMMRL_POLICY_TARGETS__*``."""
    runs = tuple(c for p in reward2 for c in checkpoint_files(p))
    r2 = runs or (checkpoint_file(SHIPPED[2]),)
    label = "4a DAMMRL, Reward 2, adaptive (S3 re-selection)"
    policy = PolicySpec("adaptive", checkpoints=r2[:1])
    return Configuration("4a-adaptive-r2", label, "ours", "event", policy)


def reviewer_configurations() -> list[Configuration]:
    """The random-choice row; the best-fixed rows are made once the search has run."""
    return [
        Configuration("random", "event-triggered, uniformly random (i, j)", "reviewer", "event",
                      PolicySpec("random")),
    ]  # fmt: skip


def best_fixed_candidates() -> list[Configuration]:
    """Every M_ij under each progression (fixed-frequency as configuration 1)."""
    bases = (
        Configuration("best-fixed", "best fixed model, fixed-frequency", "reviewer", "fixed",
                      PolicySpec("fixed"), PAPER_FIXED),
        Configuration("best-event", "best fixed model, event-triggered", "reviewer", "event",
                      PolicySpec("fixed")),
    )  # fmt: skip
    return [base.with_model((i, j)) for base in bases for i in (1, 2) for j in range(1, 9)]
