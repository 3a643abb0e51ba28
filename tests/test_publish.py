"""The performance page's publisher says what must not be published: a figure worse than
its last published value beyond its tolerance, and a ratio to a replayed physics that was
not the physics the benchmark ran (the replay not bit for bit)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

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
