"""Where the in-process loop's and the RL environment's processor time goes: each part's
exclusive share (a part's time less the parts it calls), measured by timing the parts'
own functions with the process clock (about a microsecond of timing per call, counted in
the part that made it). The physics is MuJoCo's own calls (``mj_step`` and the rollouts);
the rest is the Python around it.

    python benchmarks/loop_profile.py [--reaches 10] [--decisions 300] [--randomised]
"""

from __future__ import annotations

import argparse
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from typing import Any

import mujoco
import numpy as np
from mujoco import rollout

import dammrl.stack.runner as runner_module
import dammrl_core.sim.simulation as simulation_module
from dammrl.learning.rl import env as env_module
from dammrl.learning.rl.config import RewardWeights
from dammrl.learning.rl.env import ACTIONS, ReachEnv
from dammrl.stack.runner import ReachRunner, ReachSettings
from dammrl_core.control import controller, reach, trajectory
from dammrl_core.ik import DampedLeastSquaresIK

# (owner, attribute, part): the functions timed, each charged to its part
PARTS: list[tuple[Any, str, str]] = [
    (rollout.Rollout, "rollout", "physics (MuJoCo)"),
    (simulation_module.Simulation, "coast", "coast: stepping loop, sensor rows, noise"),
    (simulation_module.Simulation, "rewind", "coast: stepping loop, sensor rows, noise"),
    (simulation_module.Simulation, "advance", "idle fast-forward"),
    (runner_module.Episode, "_fast_forward", "idle fast-forward"),
    (runner_module.Episode, "_coast", "coast: runner's bookkeeping"),
    (controller.Controller, "reference_inputs", "coast: reference and torques ahead"),
    (reach.Reach, "first_event", "coast: event search"),
    (reach.Reach, "coast", "coast: logging"),
    (reach.Reach, "tick", "tick: supervisor and controller"),
    (controller.Controller, "_plan", "tick: planning a step (micro-step, checks)"),
    (trajectory.QuinticSegment, "plan", "tick: planning a step (micro-step, checks)"),
    (DampedLeastSquaresIK, "solve", "tick: IK solve"),
    (simulation_module.Simulation, "read", "sim: read, apply, step call"),
    (simulation_module.Simulation, "apply", "sim: read, apply, step call"),
    (simulation_module.Simulation, "step", "sim: read, apply, step call"),
    (simulation_module.Simulation, "reset", "episode start (start posture, reset)"),
    (runner_module.ReachRunner, "episode", "episode start (start posture, reset)"),
    (runner_module.Episode, "_ask_human", "simulated human"),
    (runner_module.Episode, "result", "metrics of a finished reach"),
    (env_module.ReachEnv, "_terms", "environment: reward terms"),
    (env_module.ReachEnv, "_observation", "environment: observation"),
]


class Clock:
    """Exclusive processor time per part: a timed call's time, less its timed callees'."""

    def __init__(self) -> None:
        self.spent: dict[str, float] = defaultdict(float)
        self.calls: Counter[str] = Counter()  # by function name
        self._stack: list[float] = []  # the callees' time of each open call

    def timed(self, function: Callable[..., Any], part: str) -> Callable[..., Any]:
        name = function.__qualname__

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            self.calls[name] += 1
            self._stack.append(0.0)
            start = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                elapsed = time.process_time() - start
                self.spent[part] += elapsed - self._stack.pop()
                if self._stack:
                    self._stack[-1] += elapsed

        return wrapper

    def install(self) -> None:
        for owner, name, part in PARTS:
            setattr(owner, name, self.timed(getattr(owner, name), part))
        step = self.timed(mujoco.mj_step, "physics (MuJoCo)")
        simulation_module.mujoco.mj_step = step  # type: ignore[attr-defined]


def reaches(runner: ReachRunner, n: int) -> None:
    for seed in range(n):
        runner.run(seed, (1, 1), trigger="event")


def decisions(runner: ReachRunner, n: int) -> None:
    env = ReachEnv(runner, RewardWeights.preset(2), max_decisions=150)
    rng, episode = np.random.default_rng(0), 0
    env.reset(seed=episode)
    for _ in range(n):
        *_, terminated, truncated, _ = env.step(
            (rng.integers(ACTIONS[0]), rng.integers(ACTIONS[1]))
        )
        if terminated or truncated:
            episode += 1
            env.reset(seed=episode)


EVENTS = (("Reach.tick", "ticks"), ("Episode._coast", "stretches of quiet ticks"),
          ("DampedLeastSquaresIK.solve", "IK solves (micro-steps planned)"))  # fmt: skip


def table(title: str, clock: Clock, total: float) -> None:
    physics = clock.spent["physics (MuJoCo)"]
    solves = clock.calls["DampedLeastSquaresIK.solve"]
    rest = total - physics
    print(f"{title}: {total:.2f} processor s, physics {physics:.2f} s, the rest {rest:.2f} s")
    print("events: " + ", ".join(f"{clock.calls[name]} {what}" for name, what in EVENTS))
    if solves:
        print(f"per micro-step: physics {physics / solves * 1e3:.2f} ms, the rest "
              f"{rest / solves * 1e3:.2f} ms")  # fmt: skip
    print("| part | share |\n|---|---|")
    unattributed = total - sum(clock.spent.values())
    rows = [*clock.spent.items(), ("the loop itself and the rest", unattributed)]
    for part, spent in sorted(rows, key=lambda row: -row[1]):
        print(f"| {part} | {spent / total:.1%} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reaches", type=int, default=10)
    parser.add_argument("--decisions", type=int, default=300)
    parser.add_argument("--randomised", action="store_true", help="the randomised arm")
    args = parser.parse_args()
    runner = ReachRunner(ReachSettings().randomized(args.randomised))
    runner.run(0)  # warm up (imports, caches)
    clock = Clock()
    clock.install()
    arm = "randomised" if args.randomised else "nominal"
    for title, work in (
        (f"{args.reaches} whole event reaches, {arm} arm", lambda: reaches(runner, args.reaches)),
        (f"RL environment, {args.decisions} decisions, {arm} arm",
         lambda: decisions(runner, args.decisions)),
    ):  # fmt: skip
        clock.spent.clear()
        clock.calls.clear()
        start = time.process_time()
        work()
        table(title, clock, time.process_time() - start)


if __name__ == "__main__":
    main()
