"""The performance page's publisher says what must not be published: a figure worse than
its last published value beyond its tolerance, and a ratio to a replayed physics that was
not the physics the benchmark ran (the replay not bit for bit)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _publish() -> ModuleType:
    spec = importlib.util.spec_from_file_location("publish", ROOT / "benchmarks" / "publish.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["publish"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _runs(loop: float, bitwise: bool) -> dict[str, Any]:
    figures = {"loop / raw mj_step": loop, "replayed bit for bit": bitwise}
    return {"core": {"date": "2026-11-28", "figures": figures}}


def test_a_replay_that_was_not_bit_for_bit_is_reported() -> None:
    publish = _publish()
    assert publish.baselines_off(_runs(0.8, True)) == []
    (line,) = publish.baselines_off(_runs(0.8, False))
    assert line.startswith("baseline off: core's replayed physics was not bit for bit")


def test_a_figure_beyond_its_tolerance_is_a_regression() -> None:
    publish = _publish()
    published = _runs(0.80, True)
    assert publish.regressions(_runs(0.75, True), published) == []  # within 10 %
    (line,) = publish.regressions(_runs(0.70, True), published)
    assert "in-process loop / raw mj_step is 0.70, published 0.80" in line


def test_the_page_says_which_states_make_the_p99() -> None:
    publish = _publish()
    ticks = {"quiet": {"ticks": 1400, "p50": 380.0, "p90": 520.0, "p99": 700.0,
                       "among the 1 % slowest": 12},
             "started a step": {"ticks": 20, "p50": 470.0, "p90": 600.0, "p99": 900.0,
                                "among the 1 % slowest": 3}}  # fmt: skip
    machine = {
        "processor": "a CPU",
        "cores": 2,
        "system": "Linux",
        "python": "3.11",
        "load average (1 min)": 0.4,
    }
    record = {"bus": {"date": "2026-11-28", "commit": "abc", "machine": machine,
                      "figures": {"variants": {"as built": {"ticks": ticks}}}}}  # fmt: skip
    page = publish.section(record)
    assert "Which states make the p99" in page
    assert "| quiet | 1400 | 380 / 520 / 700 | 12 |" in page
    assert "| started a step | 20 | 470 / 600 / 900 | 3 |" in page


def _bench_bus() -> ModuleType:
    sys.path.insert(0, str(ROOT / "benchmarks"))  # it imports bus_variants beside it
    try:
        spec = importlib.util.spec_from_file_location(
            "bench_bus", ROOT / "benchmarks" / "bench_bus.py"
        )
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return module


def _bus_round(bus: ModuleType, p99_ms: float, bare_p99_ms: float) -> dict[str, Any]:
    spans = {"p50": 1.0, "p99": p99_ms, "p99.9": p99_ms}
    return {"round trip [ms]": spans, "bare Zenoh [ms]": {"p50": 0.5, "p99": bare_p99_ms},
            "legs [ms]": dict.fromkeys(bus.LEGS, spans), "states": 1000, "commands per state": 1.0,
            "periods on their own answer": 1.0, "start-up [s]": 1.0,
            "real-time factor": 1.0}  # fmt: skip


def test_the_bus_goal_is_read_on_the_median_round_with_its_interval() -> None:
    """Twelve rounds: the median ratio's interval runs from the 3rd to the 10th smallest
    round, and the page says how many rounds are at or under 2, and every round."""
    ratios = [1.2, 2.6, 1.5, 1.9, 3.1, 1.4, 1.7, 2.2, 1.6, 1.8, 1.3, 2.05]
    bus = _bench_bus()
    figures = bus.summary([_bus_round(bus, 2 * r, 2.0) for r in ratios])
    ordered = sorted(ratios)
    assert figures["p99 / bare p99, 95 % interval"] == (ordered[2], ordered[9])
    assert figures["p99 / bare p99"] == (ordered[5] + ordered[6]) / 2
    line = _publish()._ratio_line("as built", figures)
    assert "median 1.75, 95 % interval 1.40 to 2.20" in line
    assert "8 of 12 rounds at or under 2" in line
    every = "1.20, 1.30, 1.40, 1.50, 1.60, 1.70, 1.80, 1.90, 2.05, 2.20, 2.60, 3.10."
    assert line.endswith(every)


def test_a_refused_publish_keeps_its_runs_and_publishes_them_later(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Half an hour of measuring is not lost to a regression: the runs are kept, and
    ``--runs`` publishes them without measuring again."""
    publish = _publish()
    machine = {"processor": "a CPU", "cores": 2, "system": "Linux", "python": "3.11",
               "load average (1 min)": 0.1}  # fmt: skip
    published = {"core": {"date": "2026-11-27", "commit": "old", "machine": machine,
                          "figures": {"loop / raw mj_step": 0.80}}}  # fmt: skip
    measured = {"core": {"date": "2026-11-28", "commit": "new", "machine": machine,
                         "figures": {"loop / raw mj_step": 0.70}}}  # fmt: skip
    page, record = tmp_path / "performance.md", tmp_path / "performance.json"
    page.write_text(f"# Performance\n{publish.BEGIN}\nold\n{publish.END}\nafter\n")
    record.write_text(json.dumps(published))
    kept = tmp_path / "kept.json"
    monkeypatch.setattr(publish, "KEPT", kept)
    monkeypatch.setattr(publish, "run", lambda names, quick: measured)
    files = ["--page", str(page), "--published", str(record), "--only", "core"]
    monkeypatch.setattr(sys, "argv", ["publish.py", *files])
    assert publish.main() == 1  # 0.70 against 0.80: beyond 10 %
    assert "old" in page.read_text() and json.loads(record.read_text()) == published
    assert json.loads(kept.read_text()) == measured

    monkeypatch.setattr(publish, "run", lambda names, quick: pytest.fail("measured again"))
    monkeypatch.setattr(sys, "argv", ["publish.py", *files, "--runs", str(kept), "--accept"])
    assert publish.main() == 0
    assert json.loads(record.read_text())["core"]["commit"] == "new"
    assert "| in-process loop / raw mj_step | 0.70 |" in page.read_text()
    assert page.read_text().endswith(f"{publish.END}\nafter\n")


def test_the_page_says_whether_each_goal_is_met() -> None:
    """A goal is met on the value, and for the bus's median round only when its whole
    interval says so; a figure with no goal gets no verdict."""
    publish = _publish()

    def bus(median: float, interval: tuple[float, float]) -> dict[str, Any]:
        built = {"p99 / bare p99": median, "p99 / bare p99, 95 % interval": list(interval)}
        return {"bus": {"figures": {"variants": {"as built": built}}}}

    ratio = next(f for f in publish.FIGURES if f.label == "bus p99 / bare Zenoh p99")
    assert ratio.verdict(bus(1.6, (1.4, 1.9))) == "met"
    assert ratio.verdict(bus(2.2, (2.01, 2.4))) == "not met"
    assert ratio.verdict(bus(1.9, (1.5, 2.3))) == "unresolved"
    loop = next(f for f in publish.FIGURES if f.label == "in-process loop / raw mj_step")
    assert loop.verdict(_runs(0.91, True)) == "met"
    assert loop.verdict(_runs(0.76, True)) == "not met"
    replay = next(f for f in publish.FIGURES if f.goal == "" and f.benchmark == "core")
    assert replay.verdict({"core": {"figures": {replay.path[0]: 0.5}}}) == ""
    assert loop.verdict({}) == ""  # not measured


@pytest.mark.parametrize("content", [None, "{not json", '["a list"]', '{"bus": {"date": 1}}'])
def test_runs_that_are_not_kept_runs_get_a_one_line_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, content: str | None
) -> None:
    publish = _publish()
    kept = tmp_path / "kept.json"
    if content is not None:
        kept.write_text(content)
    record = tmp_path / "performance.json"
    monkeypatch.setattr(sys, "argv", ["publish.py", "--runs", str(kept), "--published",
                                      str(record), "--page", str(tmp_path / "p.md")])  # fmt: skip
    with pytest.raises(SystemExit) as stopped:
        publish.main()
    message = str(stopped.value.code)
    assert message.startswith(f"--runs {kept}: ") and "\n" not in message
    assert not record.exists()
