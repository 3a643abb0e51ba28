"""The in-process loop's shortcuts change no result: stretches of quiet ticks stepped in one
go, the idle fast-forward, the oscillation filter's cached initial conditions. Each is
checked bit for bit against ticking every control period (the loop as it was before any
shortcut): whole reaches, the RL environment's steps and a training run."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.signal import sosfiltfilt

from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.env import ACTIONS, ReachEnv
from dammrl.learning.rl.train import train
from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings
from dammrl_core.control.controller import Controller, ReferenceInputs
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.control.trajectory import QuinticSegment
from dammrl_core.metrics import _low_pass, motion_estimate


def assert_same_reach(fast: ReachResult, ticked: ReachResult) -> None:
    assert fast.summary() == ticked.summary()
    for field in dataclasses.fields(fast.trajectory):
        np.testing.assert_array_equal(
            getattr(fast.trajectory, field.name), getattr(ticked.trajectory, field.name),
            err_msg=field.name,
        )  # fmt: skip
    measured = {"ik_compute_s": 0.0}  # the solver's own clock: differs run to run anyway
    assert [repr(dataclasses.replace(s, **measured)) for s in fast.steps] == [
        repr(dataclasses.replace(s, **measured)) for s in ticked.steps
    ]
    assert repr(fast.decisions) == repr(ticked.decisions)
    assert repr(fast.choices) == repr(ticked.choices)


@pytest.mark.parametrize("randomized", [False, True], ids=["nominal", "randomised"])
def test_whole_reaches_are_bitwise_those_of_ticking_every_period(randomized: bool) -> None:
    fast = ReachRunner(ReachSettings().randomized(randomized))
    ticking = ReachRunner(ReachSettings(fast_forward=False).randomized(randomized))
    for seed, model in ((0, (1, 1)), (1, (2, 1)), (2, (1, 8)), (3, (2, 6))):
        assert_same_reach(fast.run(seed, model), ticking.run(seed, model))


@pytest.mark.parametrize("randomized", [False, True], ids=["nominal", "randomised"])
def test_a_step_started_within_a_stretch_is_the_step_started_by_its_tick(
    randomized: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A solve waiting out its latency starts its step inside a stretch of quiet ticks
    (no tick of its own), and the reach is the ticked one."""
    settle, started = Controller.settle, []

    def counting_settle(self: Controller, inputs: ReferenceInputs, ran: int) -> Any:
        command, steps = settle(self, inputs, ran)
        started.extend(steps)
        return command, steps

    monkeypatch.setattr(Controller, "settle", counting_settle)
    fast = ReachRunner(ReachSettings().randomized(randomized)).run(5, (1, 3))
    ticking = ReachRunner(ReachSettings(fast_forward=False).randomized(randomized)).run(5, (1, 3))
    assert started and len(started) >= len(fast.steps) // 2  # most steps start in bulk
    assert_same_reach(fast, ticking)


@pytest.mark.parametrize(
    "controller",
    [ControllerSettings(trigger="fixed"), ControllerSettings(feedforward="resolved_acceleration")],
    ids=["fixed-frequency", "resolved-acceleration"],
)
def test_the_other_controllers_reach_as_when_ticked(controller: ControllerSettings) -> None:
    fast = ReachRunner(ReachSettings(controller=controller))
    ticking = ReachRunner(ReachSettings(controller=controller, fast_forward=False))
    assert_same_reach(fast.run(4, (2, 1)), ticking.run(4, (2, 1)))


def _environment_steps(runner: ReachRunner, decisions: int) -> list[Any]:
    env = ReachEnv(runner, RewardWeights.preset(2), max_decisions=40)
    rng, episode = np.random.default_rng(7), 0
    seen: list[Any] = [env.reset(seed=episode)[0].tolist()]
    for _ in range(decisions):
        action = (int(rng.integers(ACTIONS[0])), int(rng.integers(ACTIONS[1])))
        obs, reward, terminated, truncated, info = env.step(action)
        seen.append((obs.tolist(), reward, terminated, truncated, repr(info["terms"])))
        if terminated or truncated:
            seen.append(repr(info["metrics"]))
            episode += 1
            seen.append(env.reset(seed=episode)[0].tolist())
    return seen


@pytest.mark.parametrize("randomized", [False, True], ids=["nominal", "randomised"])
def test_the_environment_steps_as_when_ticked(randomized: bool) -> None:
    fast = ReachRunner(ReachSettings().randomized(randomized))
    ticking = ReachRunner(ReachSettings(fast_forward=False).randomized(randomized))
    assert _environment_steps(fast, 60) == _environment_steps(ticking, 60)


def test_training_rewards_are_those_of_the_ticked_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = TrainSettings(episodes=3, max_decisions=25, learning_starts=20, batch_size=8)
    fast = train(2, tmp_path / "fast", settings, "cpu", progress=lambda _: None)
    monkeypatch.setattr(
        "dammrl.learning.rl.train.ReachSettings", lambda: ReachSettings(fast_forward=False)
    )
    ticked = train(2, tmp_path / "ticked", settings, "cpu", progress=lambda _: None)
    np.testing.assert_array_equal(
        [list(dataclasses.astuple(log)) for log in fast],
        [list(dataclasses.astuple(log)) for log in ticked],
    )


def test_the_motion_filter_is_scipys_sosfiltfilt_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    sos, _ = _low_pass(10.0, 100.0)
    for n in (16, 17, 28, 29, 40, 300):
        x = np.cumsum(rng.normal(0.0, 1e-3, (n, 3)), axis=0)
        expected = sosfiltfilt(sos.copy(), x, axis=0, padlen=min(n - 1, 27))
        np.testing.assert_array_equal(motion_estimate(x, 100.0), expected)


def test_a_reference_sampled_in_bulk_is_the_reference_sampled_per_tick() -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        q0, v0, a0, q1 = (rng.normal(0.0, 1.0, 6) for _ in range(4))
        segment = QuinticSegment.plan(rng.uniform(0, 9), rng.uniform(0.08, 2), q0, v0, a0, q1)
        times = segment.t0_s + np.sort(rng.uniform(-0.01, segment.duration_s + 0.05, 30))
        bulk = segment.sample_many(times)
        for k, t in enumerate(times):
            for row, value in zip(bulk, segment.sample(float(t)), strict=True):
                np.testing.assert_array_equal(row[k], value)
