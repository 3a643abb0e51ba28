"""The co-adaptation comparison as a report: the verdict of every registered rule, a
section per kind of person, the regret curves, the levels figure and the JSON."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from dammrl.learning.adapt import RefineSettings, deployment_rate
from dammrl.study.coadaptation import (
    MARGIN_COMFORT,
    MARGIN_S,
    SESSION_REACHES,
    SETTLE_REACHES,
    TARGETS,
    LongRun,
    PersonResult,
    Plan,
    Row,
    Verdict,
    arm_rows,
    difference,
    regret_curve,
    verdict,
)
from dammrl.study.stats import Estimate, bootstrap_mean, wilson
from dammrl_core.model_table import BASE, option_name

MIN_ORACLE_SEEDS = 30
"""Seeds per option below which the best fixed model is not called the oracle."""
ARMS = ("shipped", "oracle", "adaptive", "interpolated", "as deployed")


def oracle_label(seeds: int) -> str:
    if seeds >= MIN_ORACLE_SEEDS:
        return "oracle"
    return f"best fixed on {seeds} seeds (too few to be an oracle)"


def write_report(results: list[PersonResult], plan: Plan, out: Path,
                 registration: str = "") -> Path:  # fmt: skip
    """report.md, results.json, regret.png and coadaptation.png in ``out``; the report."""
    out.mkdir(parents=True, exist_ok=True)
    verdicts = [verdict(r) for r in results]
    seeds = len(plan.oracle_seeds)
    lines = [
        "# Co-adaptation: shipped, adaptive, refined and oracle policy per kind of person",
        "",
        registration,
        "",
        f"Targets over the last {TARGETS.window} reaches: success >= {TARGETS.success_min:.0%}, "
        f"median time <= {TARGETS.time_max_s:g} s, comfort >= {TARGETS.comfort_min:g}. "
        f"{len(plan.test_seeds)} test seeds ({plan.test_seeds.start:,}-"
        f"{plan.test_seeds.stop - 1:,}) as the person's sessions 2-"
        f"{1 + -(-len(plan.test_seeds) // SESSION_REACHES)} of {SESSION_REACHES} reaches; the "
        f"{oracle_label(seeds)} searched on {seeds} seeds per M_ij "
        f"({plan.oracle_seeds.start:,}+); the adaptive mode {plan.replicates} times (Thompson "
        f"seeds 0-{plan.replicates - 1}), with interpolation {plan.interpolated_replicates} "
        f"times; the refinement on a first session of "
        f"{len(plan.session_seeds)} reaches.",
        "",
        "Time to success: a failed reach counts the 60 s horizon. Intervals are 95 % "
        "(success: Wilson; the rest: bootstrap over seeds, replicates averaged within a "
        "seed); differences are paired by seed.",
        "",
        *summary_table(results, verdicts),
        "",
        *goals_table(results, verdicts),
        "",
        *gate_rates_table(results, plan),
        "",
        "![cumulative regret against the oracle](regret.png)",
        "",
        "![levels per kind of person and policy](coadaptation.png)",
        "",
    ]
    for result, v in zip(results, verdicts, strict=True):
        lines += _person(result, v, seeds)
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    data = [_json(r, v) for r, v in zip(results, verdicts, strict=True)]
    (out / "results.json").write_text(json.dumps(data, indent=1) + "\n")
    _levels_figure(results, out / "coadaptation.png")
    _regret_figure(results, out / "regret.png")
    return report


def summary_table(results: list[PersonResult], verdicts: list[Verdict]) -> list[str]:
    lines = [
        "| person | case | oracle (search; test success) | shipped: success, time to success [s] "
        "| adaptive - shipped [s] | adaptive - oracle after "
        f"{SETTLE_REACHES} [s] | interpolated - adaptive [s] | refined | switches (mean) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for result, v in zip(results, verdicts, strict=True):
        arms, seeds = result.arms, _seeds(result)
        oracle = LongRun.of(result.search[result.oracle])
        test_success = np.mean([r.success for r in arms["oracle"]])
        shipped = f"{_success(arms['shipped'])}, {_mean(arms['shipped'], _time).text(1, 1)}"
        vs_shipped = difference(arms["adaptive"], arms["shipped"], _time, seeds, stream=11)
        vs_oracle = difference(arms["adaptive"], arms["oracle"], _time, seeds, SETTLE_REACHES, 12)
        interpolated = "n/a"
        if arms.get("interpolated"):
            diff = difference(arms["interpolated"], arms["adaptive"], _time, seeds, stream=13)
            interpolated = diff.text(1, 2)
        gate = result.refined.gate
        refined = "deployed" if gate.deployed else f"kept (gain {gate.gain.text(1)} s)"
        switches = np.mean([len(s.switches) for s in result.sessions if not s.interpolate])
        lines.append(
            f"| {result.kind.name} | {v.case} | {option_name(result.oracle)} "
            f"({oracle.success:.0%}, {oracle.median_time_s:.1f} s, comfort {oracle.comfort:.1f}; "
            f"{test_success:.0%}) | {shipped} | {vs_shipped.text(1, 2)} | "
            f"{vs_oracle.text(1, 2)} | {interpolated} | {refined} | {switches:.1f} |"
        )
    return lines


def goals_table(results: list[PersonResult], verdicts: list[Verdict]) -> list[str]:
    lines = ["| person | goal | verdict | measured |", "|---|---|---|---|"]
    for result, v in zip(results, verdicts, strict=True):
        verdict_text = "no goal" if v.passed is None else ("met" if v.passed else "NOT met")
        lines.append(f"| {result.kind.name} | {v.goal} | {verdict_text} | {v.detail} |")
        goal3 = "nothing deployed" if v.goal3 is None else ("met" if v.goal3 else "NOT met")
        lines.append(f"| {result.kind.name} | goal 3 | {goal3} | {v.goal3_detail} |")
    return lines


def gate_rates_table(results: list[PersonResult], plan: Plan) -> list[str]:
    """The gate's false-positive rate and power for each kind of person, on the per-seed
    gains of the refined candidate over the shipped policy on the test seeds (a larger
    sample of how two such policies differ than the gate's own), shifted to a true gain
    of 0 and of the margin: at this comparison's gate size and at ``dammrl adapt``'s."""
    sizes = sorted({plan.refine.gate_seeds, RefineSettings().gate_seeds})
    lines = [
        f"The gate's error rates: 1,000 gates of {' and of '.join(map(str, sizes))} reaches "
        "each, drawn from the per-seed gains (shipped minus refined time to success) on the "
        "test seeds, shifted to a true mean gain of 0 s (deployed: a false positive; nominal "
        f"2.5 %) and of {MARGIN_S:g} s (deployed: the power). This comparison's gate ran "
        f"{plan.refine.gate_seeds} reaches per policy; `dammrl adapt`'s runs "
        f"{RefineSettings().gate_seeds}.",
        "",
        "| person | gains: mean, sd [s]; seeds with a different outcome | "
        + " | ".join(f"false-positive rate, power at {MARGIN_S:g} s ({n} reaches)" for n in sizes)
        + " |",
        "|---|---|" + "---|" * len(sizes),
    ]
    for result in results:
        by_seed = {r.seed: r.restricted_s for r in result.arms["shipped"]}
        gains = np.array([by_seed[r.seed] - r.restricted_s for r in result.arms["refined"]])
        cells = []
        for n in sizes:
            false, power = (wilson(*deployment_rate(gains, true, n, plan.refine.min_gain_s))
                            for true in (0.0, MARGIN_S))  # fmt: skip
            cells.append(f"{false.text(100, 1)} %, {power.text(100, 0)} %")
        lines.append(f"| {result.kind.name} | {gains.mean():+.2f}, {gains.std(ddof=1):.2f}; "
                     f"{np.mean(gains != 0):.0%} | " + " | ".join(cells) + " |")  # fmt: skip
    return lines


def _person(result: PersonResult, v: Verdict, seeds: int) -> list[str]:
    kind = result.kind
    fit = result.refined.fit
    lines = [
        f"## {kind.name}",
        "",
        f"File `{kind.key}.yaml`. {kind.source}",
        "",
        f"**{v.case}**: {v.why}.",
        "",
        "| policy | success | time to success [s] | median time [s] | comfort |",
        "|---|---|---|---|---|",
    ]
    for arm, rows in arm_rows(result):
        lines.append(f"| {arm} | {_success(rows)} | {_mean(rows, _time).text(1, 2)} | "
                     f"{np.median([r.t_total_s for r in rows]):.1f} | "
                     f"{_mean(rows, _comfort).text(1, 2)} |")  # fmt: skip
    lines += ["", "| on the oracle's seeds | success | median time [s] | comfort | targets met |",
              "|---|---|---|---|---|"]  # fmt: skip
    for option in (BASE, result.oracle):
        run = LongRun.of(result.search[option])
        name = "the shipped policy" if option == BASE else f"{oracle_label(seeds)} "
        name += "" if option == BASE else option_name(option)
        lines.append(f"| {name} | {run.success:.0%} | {run.median_time_s:.1f} | "
                     f"{run.comfort:.1f} | {run.targets_met()} |")  # fmt: skip
    lines += ["", "Paired differences (seconds of time to success; comfort in rating points):",
              ""]  # fmt: skip
    lines += [f"- {line}" for line in _differences(result)]
    gate = result.refined.gate
    lines += [
        "",
        f"Refinement: the first session fitted the person as {fit.accuracy_big:.0%} correct "
        f"under E_big, {fit.accuracy_small:.0%} under E_small, decision times "
        f"x{fit.decision_time_factor:.2f}. Gate: "
        f"{'deployed' if gate.deployed else 'not deployed'}: {gate.reason}.",
        "",
        f"{v.goal}: {v.detail}. Goal 3: {v.goal3_detail}.",
        "",
    ]
    for session in result.sessions:
        kind_of = "interpolated" if session.interpolate else "adaptive"
        lines += [f"Switches, {kind_of} replicate {session.replicate}:", ""]
        lines += [f"- {s}" for s in session.switches or ["none"]]
        lines += [f"- (held) {h}" for h in session.held]
        lines.append("")
    return lines


def _differences(result: PersonResult) -> list[str]:
    arms, seeds = result.arms, _seeds(result)
    out = []
    pairs = [("adaptive", "shipped", 0), ("adaptive", "oracle", 0),
             ("adaptive", "oracle", SETTLE_REACHES), ("interpolated", "adaptive", 0),
             ("refined", "shipped", 0), ("oracle", "shipped", 0)]  # fmt: skip
    for k, (a, b, after) in enumerate(pairs):
        if not arms.get(a) or not arms.get(b):
            continue
        time = difference(arms[a], arms[b], _time, seeds, after, 20 + k)
        comfort = difference(arms[a], arms[b], _comfort, seeds, after, 40 + k)
        success = difference(arms[a], arms[b], _succeeded, seeds, after, 60 + k)
        when = f" (reaches after {after})" if after else ""
        out.append(f"{a} - {b}{when}: time to success {time.text(1, 2)}, success "
                   f"{success.text(100, 0)} pp, comfort {comfort.text(1, 2)}")  # fmt: skip
    return out


def _time(r: Row) -> float:
    return r.restricted_s


def _comfort(r: Row) -> float:
    return r.comfort


def _succeeded(r: Row) -> float:
    return float(r.success)


def _seeds(result: PersonResult) -> list[int]:
    return [r.seed for r in sorted(result.arms["shipped"], key=lambda r: r.index)]


def _success(rows: Sequence[Row]) -> str:
    estimate = wilson(sum(r.success for r in rows), len(rows))
    return f"{estimate.text(100, 0)} %"


def _mean(rows: Sequence[Row], value: Callable[[Row], float]) -> Estimate:
    return bootstrap_mean(np.array([value(r) for r in rows]), np.random.default_rng(0))


def _json(result: PersonResult, v: Verdict) -> dict[str, Any]:
    return {
        "person": result.kind.key,
        "name": result.kind.name,
        "source": result.kind.source,
        "oracle": list(result.oracle),
        "verdict": asdict(v),
        "gate": result.refined.gate.as_dict(),
        "fit": asdict(result.refined.fit),
        "sessions": [
            {
                "replicate": s.replicate,
                "interpolate": s.interpolate,
                "switches": s.switches,
                "held": s.held,
                "posterior": _plain(s.summary),
            }
            for s in result.sessions
        ],
        "regret_s": {
            arm: regret_curve(result, arm).round(3).tolist()
            for arm in ("shipped", "adaptive", "interpolated", "refined")
            if result.arms.get(arm)
        },
        "reaches": {arm: [_row(r) for r in rows] for arm, rows in result.arms.items()},
        "search": {option_name(o): [_row(r) for r in rows] for o, rows in result.search.items()},
    }


def _row(r: Row) -> dict[str, Any]:
    return asdict(r) | {"option": list(r.option)}


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


COLOURS = {arm: f"C{k}" for k, arm in enumerate(
    ("shipped", "oracle", "adaptive", "interpolated", "refined", "as deployed"))}  # fmt: skip
"""One colour per arm in every figure."""


def _levels_figure(results: list[PersonResult], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 0.8 * len(results) + 2), constrained_layout=True)
    y = np.arange(len(results))
    height = 0.8 / len(ARMS)
    measures: list[tuple[str, Callable[[Row], float]]] = [
        ("success [%]", lambda r: 100.0 * r.success),
        ("time to success [s] (failure: 60 s)", _time),
        ("comfort (1-5)", _comfort),
    ]
    for k, arm in enumerate(ARMS):
        offset = (k - (len(ARMS) - 1) / 2) * height
        for ax, (_, value) in zip(axes, measures, strict=True):
            estimates = [_mean(_arm(res, arm), value) for res in results]
            means = np.array([e.value for e in estimates])
            errors = np.array([[e.value - e.low for e in estimates],
                               [e.high - e.value for e in estimates]])  # fmt: skip
            ax.barh(
                y + offset,
                means,
                height=height,
                xerr=errors,
                label=arm,
                capsize=2,
                color=COLOURS[arm],
            )
    for ax, (title, _) in zip(axes, measures, strict=True):
        ax.set_yticks(y, [r.kind.name for r in results])
        ax.invert_yaxis()
        ax.set_title(title)
    for ax in axes[1:]:
        ax.set_yticklabels([])
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(ARMS))
    fig.suptitle("Co-adaptation on held-out seeds: means with 95 % intervals")
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _arm(result: PersonResult, arm: str) -> list[Row]:
    return result.deployed if arm == "as deployed" else result.arms.get(arm, [])


def _regret_figure(results: list[PersonResult], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = 4
    rows = -(-len(results) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4 * columns, 3 * rows), squeeze=False,
                             constrained_layout=True)  # fmt: skip
    for ax, result in zip(axes.flat, results, strict=False):
        for arm in ("shipped", "adaptive", "interpolated", "refined"):
            if result.arms.get(arm):
                curve = regret_curve(result, arm)
                ax.plot(np.arange(1, len(curve) + 1), curve, label=arm, color=COLOURS[arm])
        ax.axhline(0.0, color="grey", linewidth=0.5)
        for boundary in range(SESSION_REACHES, len(result.arms["shipped"]), SESSION_REACHES):
            ax.axvline(boundary + 0.5, color="grey", linewidth=0.5, linestyle=":")
        ax.set_title(result.kind.name, fontsize=9)
        ax.set_xlabel("reach")
    for ax in axes[:, 0]:
        ax.set_ylabel("cumulative regret [s]")
    for ax in list(axes.flat)[len(results) :]:
        ax.set_visible(False)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=4)
    fig.suptitle("Cumulative time-to-success regret against the oracle (dotted: sessions; "
                 f"margins: {MARGIN_S:g} s, comfort {MARGIN_COMFORT:g})")  # fmt: skip
    fig.savefig(path, dpi=100)
    plt.close(fig)
