"""The loop's speed work changes no result: whole reaches, the RL environment's steps, a
training run's rewards and a study's records hash to the digests recorded from the code
before it (``results_unchanged.json``, recorded at commit 56f1e4a; re-recorded once, when a
reset began restoring the actuators' gains: only the torque read at each reach's first
sample changed, and with it the effort and what follows from it).

Floating-point results are only reproducible bit for bit with the same libraries on the
same kind of processor, so the digests are keyed by both; elsewhere this test skips and
``test_loop_speed.py`` (every shortcut against ticking each period, in one run) still holds.
A deliberate change of results re-records them:

    PYTHONPATH=. python tests/test_results_unchanged.py --record
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import platform
import sys
import tempfile
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.env import ACTIONS, ReachEnv
from dammrl.learning.rl.train import train
from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings
from dammrl_core.control.settings import ControllerSettings

DIGESTS = Path(__file__).with_name("results_unchanged.json")
LIBRARIES = ("mujoco", "numpy", "pin", "scipy", "torch")


def platform_key() -> str:
    """What bit-for-bit floating-point results depend on besides the code."""
    libraries = ", ".join(f"{name} {version(name)}" for name in LIBRARIES)
    return f"{platform.machine()} {sys.platform}, Python {platform.python_version()}, {libraries}"


def _digest(parts: list[Any]) -> str:
    sha = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            sha.update(f"{part.dtype}{part.shape}".encode())
            sha.update(np.ascontiguousarray(part).tobytes())
        else:
            sha.update(repr(part).encode())
    return sha.hexdigest()


def reach_digest(result: ReachResult) -> str:
    """Everything a reach returns but the solver's own wall clock (``ik_compute_s``)."""
    measured = {"ik_compute_s": 0.0}
    trajectory = [getattr(result.trajectory, f.name) for f in dataclasses.fields(result.trajectory)]
    return _digest([
        result.summary(), *trajectory,
        [repr(dataclasses.replace(s, **measured)) for s in result.steps],
        result.decisions, result.choices, result.ik_latencies_s, result.ik_evaluations,
    ])  # fmt: skip


REACHES = ((0, (1, 1)), (1, (2, 1)), (2, (1, 8)), (3, (2, 6)), (4, (1, 5)), (5, (2, 3)))


def reaches(randomized: bool, controller: ControllerSettings | None = None) -> str:
    settings = ReachSettings().randomized(randomized)
    if controller is not None:
        settings = settings.model_copy(update={"controller": controller})
    runner = ReachRunner(settings)
    return _digest([reach_digest(runner.run(seed, model)) for seed, model in REACHES])


def environment(randomized: bool, decisions: int = 80) -> str:
    """Random decisions: observations, rewards, their terms, the episodes' metrics."""
    env = ReachEnv(ReachRunner(ReachSettings().randomized(randomized)), RewardWeights.preset(2),
                   max_decisions=40)  # fmt: skip
    rng, episode = np.random.default_rng(11), 0
    seen: list[Any] = [env.reset(seed=episode)[0]]
    for _ in range(decisions):
        action = (int(rng.integers(ACTIONS[0])), int(rng.integers(ACTIONS[1])))
        obs, reward, terminated, truncated, info = env.step(action)
        seen += [obs, reward, terminated, truncated, info["terms"], info["model"]]
        if terminated or truncated:
            seen.append(info["metrics"])
            episode += 1
            seen.append(env.reset(seed=episode)[0])
    return _digest(seen)


def training() -> str:
    """A short training run's per-episode log (rewards, decisions, outcomes)."""
    settings = TrainSettings(episodes=4, max_decisions=25, learning_starts=20, batch_size=8)
    with tempfile.TemporaryDirectory() as out:
        logs = train(2, Path(out), settings, "cpu", progress=lambda _: None)
    return _digest([dataclasses.astuple(log) for log in logs])


def study() -> str:
    """A study's records (rows and steps) for its fixed-model configurations and a random
    policy, on the nominal and the randomised arm and with ikpy charged at the reference
    machine's solve times."""
    from dammrl.study.configs import paper_configurations, variant_configurations
    from dammrl.study.run import Job, run_job

    configurations = {c.key: c for c in paper_configurations() + variant_configurations()}
    records = []
    for key in ("1-fixed", "2-event", "1v-chained"):
        for condition in ("nominal", "randomised", "ikpy-real"):
            for seed in (7_000_000, 7_000_001):
                record = run_job(Job(configurations[key], seed, condition))
                records += [sorted(record.row.items()), record.steps, record.ik_latencies]
    return _digest(records)


CASES: dict[str, Callable[[], str]] = {
    "reaches, nominal": lambda: reaches(False),
    "reaches, randomised": lambda: reaches(True),
    "reaches, fixed frequency": lambda: reaches(True, ControllerSettings(trigger="fixed")),
    "reaches, resolved acceleration": lambda: reaches(
        False, ControllerSettings(feedforward="resolved_acceleration")
    ),
    "environment, nominal": lambda: environment(False),
    "environment, randomised": lambda: environment(True),
    "training": training,
    "study": study,
}


def _recorded() -> dict[str, str]:
    recorded = json.loads(DIGESTS.read_text())
    if recorded["platform"] != platform_key():
        pytest.skip(f"digests recorded on {recorded['platform']}; here {platform_key()}")
    return dict(recorded["digests"])


@pytest.mark.parametrize("case", list(CASES))
def test_results_are_those_recorded_before_the_speed_work(case: str) -> None:
    assert CASES[case]() == _recorded()[case], f"{case}: the results changed"


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        sys.exit(__doc__)
    digests = {case: compute() for case, compute in CASES.items()}
    recorded = {"platform": platform_key(), "digests": digests}
    DIGESTS.write_text(json.dumps(recorded, indent=1) + "\n")
    print(json.dumps(digests, indent=1))
