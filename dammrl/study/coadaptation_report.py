"""The co-adaptation comparison as a report: a table per person, a figure, the JSON."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from dammrl.study.coadaptation import SESSION_SEEDS, PersonResult, figures, settled_after
from dammrl_core.coadaptation import Targets

ARMS = ("oracle", "shipped", "adaptive", "refined")


def write_report(results: list[PersonResult], targets: Targets, out: Path) -> Path:
    """report.md, results.json and coadaptation.png in ``out``; the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Co-adaptation: oracle, shipped, adaptive and refined policy per kind of person",
        "",
        f"Targets over the last {targets.window} reaches: "
        + ", ".join(
            f"{k} {v}" for k, v in targets.model_dump().items() if v is not None and k != "window"
        ),
        "",
        "Success: Wilson 95 % interval; time and error: bootstrap 95 % intervals; "
        "'- shipped': paired by seed (bootstrap over seeds).",
        "",
    ]
    lines += [*summary_table(results), ""]
    for result in results:
        lines += _person(result)
    report = out / "report.md"
    report.write_text("\n".join(lines) + "\n")
    (out / "results.json").write_text(json.dumps([_json(r) for r in results], indent=1) + "\n")
    _figure(results, out / "coadaptation.png")
    return report


def summary_table(results: list[PersonResult]) -> list[str]:
    """One row per person: the shipped policy's level, the others' paired differences."""
    lines = ["| person | oracle M_ij | shipped: success, time [s] | adaptive - shipped: "
             "success [pp], time [s] | refined - shipped: success [pp], time [s] | switches |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for result in results:
        got = {(arm, measure): e for arm, measure, e in figures(result)}
        cells = []
        for arm in ("adaptive", "refined"):
            success = got[(arm, "success - shipped")].text(100, 0)
            cells.append(f"{success}, {got[(arm, 'time [s] - shipped')].text(1, 2)}")
        level, time = got[("shipped", "success")], got[("shipped", "time [s]")]
        shipped = f"{level.text(100, 0)} %, {time.text(1, 2)}"
        i, j = result.oracle
        lines.append(f"| {result.person} | M_{i},{j} | {shipped} | {cells[0]} | {cells[1]} | "
                     f"{len(result.session.switches)} |")  # fmt: skip
    return lines


def _person(result: PersonResult) -> list[str]:
    session = result.session
    o_i, o_j = result.oracle
    lines = [
        f"## {result.person}",
        "",
        f"Oracle (best fixed model on its own seeds): M_{o_i},{o_j}. "
        f"Posterior's MAP model settled after {settled_after(session.map_models)} of "
        f"{len(session.map_models)} reaches (last: M_{session.map_models[-1][0]},"
        f"{session.map_models[-1][1]}).",
        "",
        "| policy | measure | estimate |",
        "|---|---|---|",
    ]
    for arm, measure, estimate in figures(result):
        scale, digits = (100.0, 0) if measure.startswith("success") else (1.0, 2)
        lines.append(f"| {arm} | {measure} | {estimate.text(scale, digits)} |")
    regret = _regret(result)
    fit = result.fit
    lines += [
        "",
        f"Refined on a first session of {len(SESSION_SEEDS)} reaches: the person fitted as "
        f"{fit.accuracy:.0%} toward the goal, decision times x{fit.decision_time_factor:.2f}.",
        "",
        "Regret against the oracle (success pp, mean time s): "
        + "; ".join(f"{arm} {pp:+.0f} pp, {s:+.2f} s" for arm, (pp, s) in regret.items())
        + ".",
        "",
    ]
    lines += ["Switches:", ""] + [f"- {s}" for s in session.switches or ["none"]] + [""]
    return lines


def _regret(result: PersonResult) -> dict[str, tuple[float, float]]:
    oracle = result.arms["oracle"]
    best_success = float(np.mean([r.success for r in oracle])) * 100
    best_time = float(np.mean([r.t_total_s for r in oracle]))
    return {
        arm: (
            best_success - float(np.mean([r.success for r in rows])) * 100,
            float(np.mean([r.t_total_s for r in rows]) - best_time),
        )
        for arm, rows in result.arms.items()
        if arm != "oracle"
    }


def _json(result: PersonResult) -> dict[str, object]:
    return {
        "person": result.person,
        "oracle": list(result.oracle),
        "figures": [{"policy": a, "measure": m, **asdict(e)} for a, m, e in figures(result)],
        "regret": _regret(result),
        "switches": result.session.switches,
        "refined_fit": asdict(result.fit),
        "map_settled_after": settled_after(result.session.map_models),
        "posterior": {
            k: (v if not isinstance(v, dict) else {str(kk): vv for kk, vv in v.items()})
            for k, v in result.session.summary.items()
        },
        "reaches": {arm: [asdict(r) for r in rows] for arm, rows in result.arms.items()},
    }


def _figure(results: list[PersonResult], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 0.7 * len(results) + 2), constrained_layout=True)
    y = np.arange(len(results))
    height = 0.8 / len(ARMS)
    for k, arm in enumerate(ARMS):
        success = [np.mean([r.success for r in res.arms[arm]]) * 100 for res in results]
        times = [np.mean([r.t_total_s for r in res.arms[arm]]) for res in results]
        offset = (k - (len(ARMS) - 1) / 2) * height
        axes[0].barh(y + offset, success, height=height, label=arm)
        axes[1].barh(y + offset, times, height=height, label=arm)
    for ax, title in zip(axes, ("success [%]", "mean reach time [s]"), strict=True):
        ax.set_yticks(y, [r.person for r in results])
        ax.invert_yaxis()
        ax.set_title(title)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(ARMS))
    fig.suptitle("Co-adaptation on held-out seeds, per kind of simulated person")
    fig.savefig(path, dpi=110)
    plt.close(fig)
