"""The paper's claims C1-C6, each judged from a study's per-reach rows: rules version 4
(version 3's judgement with a faster filter, see CLAIMS_VERSION).

The rules are fixed before the results they judge, and versioned. They are more than this
file: every file that turns reaches into verdicts (``RULE_FILES``: these rules, the
inference, the configurations, a reach's row and the metrics) is hashed, and
``tests/test_registered_rules.py`` fails when any of them differs from the hashes
registered for ``CLAIMS_VERSION`` in ``registered_rules.json``: editing the judging needs a
new version, registered (committed) before a study runs under it. Nothing here is tuned to
a result.

Each check quotes the paper's words it tests (``Rule.quote``); each claim, the sentences
those words come from (``STATEMENTS``).

How a check is judged (``dammrl.study.inference``)

- Units: a comparison that involves a learned configuration (3 and 4 run every training
  seed of their reward: reach k on run k mod n) has the training runs as units, a run's
  value the mean over its reaches (both learned: run k of each, paired); one between
  configurations that learn nothing has the reaches. Configurations are paired on the
  same reach seeds.
- An exact sign test that the median unit lies on the claimed side (any distribution of
  runs: a t-test over ten run means is not valid when a few runs hover); p is
  two-sided-equivalent, and the median's distribution-free 95 % interval excludes the
  bound when it passes (ties aside).
- A claim's checks are one family: Holm's correction keeps the chance that any passing
  check is a false positive at 5 %. A claim *holds* when every check passes after the
  correction, *partly* when some do, *does not hold* when none does.
- Success and time are judged under both criteria: the button pressed (the task as a
  person does it) and the paper's ||x - x_g|| <= eps_g. Time is the time to success under
  the criterion, restricted at the 60 s episode limit (a reach without success counts
  60 s, whether it held early or ran to the limit).

Thresholds, and why these

- eps_g, the paper's goal tolerance, is not given in the paper. The verdicts use 42 mm:
  the farthest the fingertip's centre can be from x_g while it touches the button's cap
  (cap radius plus fingertip radius), the task being to press that button. Every verdict
  under eps_g is also judged at each of ``EPS_G_RANGE_MM``: from E_small (4 mm, the human's
  finer admission radius: a goal tolerance finer than the trigger's own would judge the
  last step by a stricter rule than any step) through E_big (10 mm) to the touch distance.
- "Zero chatter" and "oscillation-free" (C3, C4): N_osc = 0 in the typical reach, read
  with the median as every check here is: the median run's share of reaches with any
  oscillation lies below one half. No threshold of ours: one half is what "typical" is.
- The stages of a reach (C3, C4): its thirds by distance to the goal, the plainest reading
  of "early", "mid-to-late" and "as the end-effector approaches the target": early, farther
  than 2/3 of the start distance; mid-to-late, 2/3 of it down to eps_g; near the target,
  1/3 of it down to eps_g. Below eps_g Algorithm 1 has stopped ("Loop until
  ||x - x_g|| <= eps_g"), so no window reaches inside it.
- "Smooth" (C4): the integrated squared jerk the paper names, lower for Reward 2 than for
  Reward 1 (a margin of zero: the paper gives none, and one of ours would be a threshold
  without a source); SPARC is shown beside it, not judged.
- ``SETTLED_SHARE`` (C6), 10 %: a Q-value curve has settled when its mean moved from the
  one-but-last tenth of training to the last by under a tenth (an order of magnitude) of
  its largest move between consecutive tenths (a straight line scores 1). The tenths: the
  paper's training-curve figure has no finer resolution to speak of convergence at.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from dammrl.study.configs import EVENT, FIXED, R1, R2
from dammrl.study.inference import (
    LEVEL,
    Side,
    SignTest,
    equivalence_test,
    holm,
    sign_test,
    unit_values,
)

CLAIMS_VERSION = 5
"""3: the v3 design (docs/results.md); 4: v3's rules with dammrl_core/metrics.py's faster
oscillation filter (issue 43: the same values, tested), registered before any study ran
under v3; 5: v4's rules with ``rows.py``'s type-only import of the runner at its new place
(``dammrl.stack.runner``, issue 41's rooms), registered before any study ran under v4. A
study names the version it was judged by."""
ALPHA = LEVEL  # family-wise, per claim (Holm)
HORIZON_S = 60.0  # time to success is restricted at the episode limit (TaskSettings'
# episode_timeout_s: tests/test_study.py keeps the two equal)
EPS_G_MM = 42  # the verdicts' eps_g: the touch distance (see above)
EPS_G_RANGE_MM = (4, 10, 20, 30, 42)  # E_small ... the touch distance: the sensitivity
SETTLED_SHARE = 0.10  # Q-value move over the last tenth, share of its fastest move (C6)
TRAINING_WINDOW = 0.10  # training curves are compared in tenths (C6)
RULE_FILES = (  # every file that turns reaches into verdicts: hashed and registered
    "dammrl/study/claims.py",
    "dammrl/study/inference.py",
    "dammrl/study/configs.py",
    "dammrl/study/rows.py",
    "dammrl_core/metrics.py",
)

Verdict = Literal["holds", "partly", "does not hold", "not tested"]
Criterion = Literal["press", "eps_g"]
CRITERIA: tuple[Criterion, ...] = ("press", "eps_g")
CRITERION_TEXT: dict[Criterion, str] = {"press": "button pressed", "eps_g": "||x - x_g|| <= eps_g"}
Rows = Sequence[dict[str, Any]]
Curves = dict[str, list[dict[str, np.ndarray]]]  # reward key -> per training seed, by column


def step_windows(eps_g_m: float, start_distance_m: float) -> dict[str, tuple[float, float]]:
    """The goal-distance windows [m] of a reach's stages where Algorithm 1 plans steps:
    (nearest, farthest], nearest at eps_g."""
    third = start_distance_m / 3
    return {
        "early": (2 * third, math.inf),
        "midlate": (eps_g_m, max(eps_g_m, 2 * third)),
        "late": (eps_g_m, max(eps_g_m, third)),
    }


def eps_column(name: str, eps_g_mm: int) -> str:
    """A row's column at one eps_g: reached, t_reached (s), midlate_step, late_step (m)."""
    unit = "_s" if name.startswith("t_") else "_m" if name.endswith("step") else ""
    return f"{name}_{eps_g_mm}mm{unit}"


# ---- the paper's words --------------------------------------------------------------

STATEMENTS = {
    "C1": ("The event trigger suppresses chatter and improves convergence and success over "
           "fixed-frequency progression",
           "\"As illustrated in Fig. [comparison], the event-driven configuration significantly "
           "reduces oscillations and improves spatial convergence compared to the "
           "fixed-frequency strategy.\" (Results); \"This event-triggered architecture "
           "ensures sufficient spatial settling before advancing, suppressing oscillations "
           "and improving success rates in object acquisition tasks.\" (Sec. Event-Driven "
           "Progression)"),
    "C2": ("Without adaptive step sizing, event-triggered progression is slow",
           "\"However, without adaptive step sizing, the Fixed-Model approach struggles to "
           "optimise reaching speed.\" (Expected Comparative Outcomes)"),
    "C3": ("Reward 1: accuracy, zero chatter, prolonged execution, small steps as the target "
           "nears",
           "\"Experiment 3 (Reward 1) is expected to demonstrate exceptional spatial accuracy "
           "and zero chatter, but at the cost of prolonged execution times, as the robot "
           "agent defaults to overly cautious, small step sizes (delta_small).\" (Expected "
           "Comparative Outcomes); \"Under Reward 1, which exclusively emphasizes spatial "
           "accuracy, the agent progressively adopts high-precision small step magnitudes as "
           "the end-effector approaches the target point, thereby minimizing terminal "
           "positional error.\" (Results)"),
    "C4": ("Reward 2: larger steps mid-to-late, faster, smooth, oscillation-free, less effort",
           "\"In contrast, when trained with Reward 2, which explicitly balances speed and "
           "accuracy, the agent exhibits a tendency to select comparatively larger step "
           "sizes, particularly in the mid-to-late stages of motion, in order to accelerate "
           "target convergence.\" (Results); \"the robot agent dynamically shifts between "
           "delta_large and delta_small to match the human's cognitive state, achieving a "
           "smooth, oscillation-free trajectory that minimises both effort and task "
           "duration.\" (Expected Comparative Outcomes)"),
    "C5": ("The fully proposed DAMMRL (Reward 2) improves success, precision and time over "
           "the fixed-frequency baseline; Reward 1, precision",
           "\"Overall, the experimental results demonstrate a progressive performance "
           "improvement from the fixed-frequency baseline to fully proposed DAMMRL "
           "architecture.\" (Results); \"the system demonstrates superior spatial precision, "
           "temporal efficiency, and task success rates compared to conventional "
           "fixed-frequency shared control approaches.\" (Conclusion); Experiment 4 is \"The "
           "complete, fully formulated architecture\"; Experiment 3 is expected to show "
           "\"exceptional spatial accuracy\" \"at the cost of prolonged execution times\""),
    "C6": ("Both agents converge during training (their Q-value curves settle)",
           "\"both models have converged during training, as shown in Fig. [q-value]\" "
           "(Results)"),
}  # fmt: skip
NOT_JUDGED = (
    "C4's \"dynamically shifts between delta_large and delta_small to match the human's "
    "cognitive state\": the paper names no figure for it (the study's step-modulation figure "
    "shows the steps against the distance to the goal)."
)


# ---- checks and claims --------------------------------------------------------------


@dataclass(frozen=True)
class Check:
    key: str  # stable id
    quote: str  # the paper's words this check tests
    what: str  # how they are tested
    text: str  # ... with the numbers
    side: Side
    bound: float
    test: SignTest
    p_holm: float = math.nan
    passed: bool = False

    @property
    def p(self) -> float:
        return self.test.p


@dataclass(frozen=True)
class Claim:
    key: str
    statement: str
    verdict: Verdict
    checks: tuple[Check, ...]

    @property
    def quote(self) -> str:
        return STATEMENTS[self.key][1]


def verdict(checks: Sequence[Check]) -> Verdict:
    if not checks:
        return "not tested"
    passed = sum(c.passed for c in checks)
    return "holds" if passed == len(checks) else "partly" if passed else "does not hold"


def judge(rows: Rows, criterion: Criterion = "press", training: Curves | None = None,
          eps_g_mm: int = EPS_G_MM) -> list[Claim]:  # fmt: skip
    """C1-C6 from the rows of one condition (and seed set) under ``criterion`` (with the
    goal tolerance ``eps_g_mm``, which also bounds the step windows); ``training``: the
    training curves of Reward 1 and 2 (C6), by run."""
    table = Table(rows, criterion, eps_g_mm)
    return [_c1(table), _c2(table), _c3(table), _c4(table), _c5(table), _c6(training or {})]


# ---- the data -----------------------------------------------------------------------


class Table:
    """Rows by configuration and seed, read under one success criterion and eps_g."""

    def __init__(self, rows: Rows, criterion: Criterion, eps_g_mm: int = EPS_G_MM) -> None:
        if eps_g_mm not in EPS_G_RANGE_MM:
            raise ValueError(f"eps_g {eps_g_mm} mm: one of {EPS_G_RANGE_MM}")
        self.criterion, self.eps_g_mm = criterion, eps_g_mm
        self.by_config: dict[str, dict[int, dict[str, Any]]] = {}
        for row in rows:
            self.by_config.setdefault(row["configuration"], {})[row["seed"]] = row

    def has(self, *configs: str) -> bool:
        return all(c in self.by_config for c in configs)

    def value(self, row: dict[str, Any], metric: str) -> float:
        """A row's figure: ``success`` and ``time`` under the criterion, ``chatter`` 1 when
        the reach oscillated at all, the step windows at this eps_g, or a column."""
        if metric == "success":
            return float(bool(row[self._success]))
        if metric == "time":
            return restricted_time(row, self._time, self._success)
        if metric == "chatter":
            return math.nan if row.get("n_osc") is None else float(row["n_osc"] > 0)
        if metric in ("midlate_step", "late_step"):
            metric = eps_column(metric, self.eps_g_mm)
        value = row.get(metric)
        return math.nan if value is None else float(value)

    @property
    def _success(self) -> str:
        if self.criterion == "press":
            return "success"
        return eps_column("reached", self.eps_g_mm)

    @property
    def _time(self) -> str:
        if self.criterion == "press":
            return "t_success_s"
        return eps_column("t_reached", self.eps_g_mm)

    def paired(self, a: str, b: str, metric: str, metric_b: str | None = None) -> np.ndarray:
        """The units' values of a - b over the seeds both ran (``metric_b``: b's figure,
        when not ``metric``; a == b compares two figures of one reach)."""
        rows_a, rows_b = self.by_config[a], self.by_config[b]
        seeds = sorted(set(rows_a) & set(rows_b))
        diffs = [self.value(rows_a[s], metric) - self.value(rows_b[s], metric_b or metric)
                 for s in seeds]  # fmt: skip
        units = [unit_of(rows_a[s], rows_b[s]) for s in seeds]
        return unit_values(np.array(diffs, dtype=float), np.array(units))

    def single(self, config: str, metric: str) -> np.ndarray:
        """The units' values of one configuration's figure."""
        rows = list(self.by_config[config].values())
        values = np.array([self.value(r, metric) for r in rows], dtype=float)
        return unit_values(values, np.array([unit_of(r) for r in rows]))


def unit_of(*rows: dict[str, Any]) -> int:
    """The unit a reach belongs to: its training run(s) when any configuration in the
    comparison has several (run k of each when both do), else the reach itself."""
    runs = [int(r.get("runs") or 0) for r in rows]
    if max(runs) <= 1:
        return int(rows[0]["seed"])
    learned = [(int(r.get("run") or 0), n) for r, n in zip(rows, runs, strict=True) if n > 1]
    if len({n for _, n in learned}) > 1 or len({k for k, _ in learned}) > 1:
        raise ValueError("two learned configurations are compared run k against run k: "
                         "they need as many training runs each")  # fmt: skip
    return learned[0][0]


def restricted_time(row: dict[str, Any], time: str = "t_success_s",
                    success: str = "success") -> float:  # fmt: skip
    """Time to success restricted at the horizon: the horizon for a reach without success."""
    t = row.get(time)
    return min(float(t), HORIZON_S) if row.get(success) and t is not None else HORIZON_S


# ---- the rules ----------------------------------------------------------------------


@dataclass(frozen=True)
class Rule:
    """One check: the paper's words, what is compared, on which side, how it is shown."""

    claim: str
    quote: str
    what: str
    a: str
    b: str | None  # None: a bound on a's own figure
    metric: str
    side: Side
    bound: float = 0.0
    metric_b: str | None = None  # b's figure, when a figure of a is compared with another
    scale: float = 1.0
    unit: str = ""
    digits: int = 2

    @property
    def key(self) -> str:
        if self.metric_b is not None:  # two figures of one configuration
            return f"{self.claim}/{self.metric}-{self.metric_b}/{self.a}"
        return f"{self.claim}/{self.metric}/{self.a}" + (f"-{self.b}" if self.b else "")


def _check(t: Table, rule: Rule) -> Check:
    if rule.b is None:
        units = t.single(rule.a, rule.metric)
        compared = f"{rule.a} {rule.metric}"
    else:
        units = t.paired(rule.a, rule.b, rule.metric, rule.metric_b)
        compared = (f"{rule.a} - {rule.b}" if rule.metric_b is None
                    else f"{rule.a} {rule.metric} - {rule.metric_b}")  # fmt: skip
    test = sign_test(units, rule.side, rule.bound)
    bound = f"{rule.bound * rule.scale:g}{rule.unit}"
    text = (f"{rule.what}: {compared} {rule.side} {bound}: "
            f"{test.text(rule.scale, rule.digits, _unit_name(t, rule))}{rule.unit}")  # fmt: skip
    return Check(rule.key, rule.quote, rule.what, text, rule.side, rule.bound, test)


def _unit_name(t: Table, rule: Rule) -> str:
    configs = [rule.a] + ([rule.b] if rule.b else [])
    learned = any(int(next(iter(t.by_config[c].values())).get("runs") or 0) > 1
                  for c in configs)  # fmt: skip
    return "training runs" if learned else "reaches"


def _claim(key: str, drafts: list[Check]) -> Claim:
    """The claim's checks, Holm-corrected as one family."""
    adjusted = holm([c.p for c in drafts])
    checks = [replace(c, p_holm=q, passed=c.test.units > 0 and q < ALPHA)
              for c, q in zip(drafts, adjusted, strict=True)]  # fmt: skip
    return Claim(key, STATEMENTS[key][0], verdict(checks), tuple(checks))


def _judged(t: Table, key: str, rules: list[Rule], needs: Callable[[Rule], bool]) -> Claim:
    return _claim(key, [_check(t, r) for r in rules if needs(r)])


def _ran(t: Table) -> Callable[[Rule], bool]:
    return lambda r: t.has(r.a, *([r.b] if r.b else []))


MM, PP = 1000.0, 100.0


def _c1(t: Table) -> Claim:
    rules = [
        Rule("C1", "significantly reduces oscillations", "fewer oscillations per reach (N_osc)",
             EVENT, FIXED, "n_osc", "below"),
        Rule("C1", "improves spatial convergence", "closer to x_g at the end", EVENT, FIXED,
             "final_error_m", "below", scale=MM, unit=" mm"),
        Rule("C1", "improving success rates", "higher success", EVENT, FIXED, "success",
             "above", scale=PP, unit=" pp"),
    ]  # fmt: skip
    return _judged(t, "C1", rules, _ran(t))


def _c2(t: Table) -> Claim:
    rules = [Rule("C2", "struggles to optimise reaching speed", "slower than Reward 2's "
                  "adaptive steps", EVENT, R2, "time", "above", unit=" s")]  # fmt: skip
    return _judged(t, "C2", rules, _ran(t))


def _c3(t: Table) -> Claim:
    rules = [
        Rule("C3", "exceptional spatial accuracy", "closer to x_g than Reward 2", R1, R2,
             "final_error_m", "below", scale=MM, unit=" mm"),
        Rule("C3", "zero chatter", "the typical reach without oscillation: share of reaches "
             "with N_osc > 0 below one half", R1, None, "chatter", "below", 0.5),
        Rule("C3", "at the cost of prolonged execution times", "slower than Reward 2", R1, R2,
             "time", "above", unit=" s"),
        Rule("C3", "small step magnitudes as the end-effector approaches the target point",
             "smaller steps than Reward 2 in the last third before eps_g", R1, R2,
             "late_step", "below", scale=MM, unit=" mm"),
        Rule("C3", "progressively adopts ... small step magnitudes", "smaller steps in the "
             "last third before eps_g than in the first third", R1, R1, "late_step", "below",
             metric_b="early_step_m", scale=MM, unit=" mm"),
    ]  # fmt: skip
    return _judged(t, "C3", rules, _ran(t))


def _c4(t: Table) -> Claim:
    rules = [
        Rule("C4", "comparatively larger step sizes, particularly in the mid-to-late stages of "
             "motion", "larger steps than Reward 1 from 2/3 of the start distance to eps_g",
             R2, R1, "midlate_step", "above", scale=MM, unit=" mm"),
        Rule("C4", "accelerate target convergence ... minimises ... task duration",
             "faster than Reward 1", R2, R1, "time", "below", unit=" s"),
        Rule("C4", "a smooth ... trajectory", "lower integrated squared jerk than Reward 1 "
             "(SPARC beside it in the tables)", R2, R1, "jerk_isj", "below", scale=1e-3,
             unit=" 10^3 m^2/s^5"),
        Rule("C4", "oscillation-free", "the typical reach without oscillation: share of "
             "reaches with N_osc > 0 below one half", R2, None, "chatter", "below", 0.5),
        Rule("C4", "minimises both effort", "less mechanical work (the reward's E_effort) "
             "than Reward 1", R2, R1, "effort_j", "below", unit=" J"),
    ]  # fmt: skip
    return _judged(t, "C4", rules, _ran(t))


def _c5(t: Table) -> Claim:
    rules = [
        Rule("C5", "superior ... task success rates", "Reward 2: higher success", R2, FIXED,
             "success", "above", scale=PP, unit=" pp"),
        Rule("C5", "superior spatial precision", "Reward 2: closer to x_g at the end", R2,
             FIXED, "final_error_m", "below", scale=MM, unit=" mm"),
        Rule("C5", "temporal efficiency", "Reward 2: faster", R2, FIXED, "time", "below",
             unit=" s"),
        Rule("C5", "exceptional spatial accuracy (Reward 1)", "Reward 1: closer to x_g at the "
             "end", R1, FIXED, "final_error_m", "below", scale=MM, unit=" mm"),
    ]  # fmt: skip
    return _judged(t, "C5", rules, _ran(t))


def _c6(training: Curves) -> Claim:
    checks = [_settled(reward, agent, runs)
              for reward, runs in sorted(training.items()) if len(runs) > 1
              for agent in ("human", "robot")]  # fmt: skip
    # (one training run: a sign test has no unit to spare; the claim is then not tested)
    return _claim("C6", checks)


def _settled(reward: str, agent: str, runs: list[dict[str, np.ndarray]]) -> Check:
    """Two one-sided sign tests over training runs: the last tenth's move within
    +-SETTLED_SHARE of the curve's fastest move."""
    moves = np.array([settling(run[f"q_{agent}"]) for run in runs])
    test = equivalence_test(moves, -SETTLED_SHARE, SETTLED_SHARE)
    what = (f"the {agent} agent's Q-value curve settled in {reward}: its last-tenth move "
            f"within +-{SETTLED_SHARE} of its fastest move")  # fmt: skip
    text = f"{what}: {test.text(1, 3, 'training runs')}"
    return Check(f"C6/{reward}/{agent}", "both models have converged during training", what,
                 text, "below", SETTLED_SHARE, test)  # fmt: skip


def settling(curve: np.ndarray, window: float = TRAINING_WINDOW) -> float:
    """How fast a training curve still moves at its end, as a share of its fastest move:
    the change of its mean from the one-but-last window to the last, over the largest such
    change between consecutive windows (0: settled; about 1: still moving as fast as it
    ever did, as a straight line does; NaN entries, before the first update, left out)."""
    q = np.asarray(curve, dtype=float)
    n = max(1, round(window * q.size))
    means = [np.nanmean(chunk) if np.isfinite(chunk).any() else np.nan
             for chunk in (q[k : k + n] for k in range(0, q.size - n + 1, n))]  # fmt: skip
    moves = np.diff(np.array(means))
    moves = moves[np.isfinite(moves)]
    fastest = float(np.max(np.abs(moves))) if moves.size else 0.0
    return float(moves[-1]) / fastest if fastest > 0 else math.nan


# ---- stability over disjoint seed sets ----------------------------------------------


@dataclass(frozen=True)
class Stability:
    """How one claim's checks fared on each disjoint seed set."""

    stable: bool  # every check passed on every set, or failed on every set
    flips: tuple[str, ...]  # the keys of checks that pass on some sets only
    sign_changes: tuple[str, ...]  # checks whose median lies on both sides of the bound
    reversals: tuple[str, ...]  # ... with the intervals of both sides excluding the bound
    verdicts: tuple[Verdict, ...]  # the claim's verdict on each set


def stability(per_set: Sequence[Claim]) -> Stability:
    """One claim judged on each disjoint set: stable only when every check agrees."""
    keys = [c.key for c in per_set[0].checks] if per_set else []
    flips, signs, reversals = [], [], []
    for m, key in enumerate(keys):
        checks = [claim.checks[m] for claim in per_set]
        if len({c.passed for c in checks}) > 1:
            flips.append(key)
        sides = {_side_of(c) for c in checks} - {0}
        if len(sides) > 1:
            signs.append(key)
            if {_side_of(c, strict=True) for c in checks} >= {-1, 1}:
                reversals.append(key)
    return Stability(not flips, tuple(flips), tuple(signs), tuple(reversals),
                     tuple(c.verdict for c in per_set))  # fmt: skip


def _side_of(check: Check, strict: bool = False) -> int:
    """+1 when the median unit lies above the bound, -1 below, 0 on it (``strict``: only
    when its interval excludes the bound)."""
    e = check.test.median
    if e.n == 0:
        return 0
    if strict:
        return 1 if e.low > check.bound else -1 if e.high < check.bound else 0
    return 1 if e.value > check.bound else -1 if e.value < check.bound else 0


def p_text(check: Check) -> str:
    return f"p = {check.p:.4f}, Holm {check.p_holm:.4f}"
