"""Control-core benchmarks, in one run on this machine (figures, not pass/fail):

(a) physics steps per processor second of the full in-process sim + controller loop
    (whole reaches: IK, human, metrics included) against raw ``mj_step`` on the same
    compiled model, with the runner's shortcuts (the idle fast-forward, stretches of quiet
    ticks in one go) and ticking every period; each the best of ``--repeat`` interleaved
    timings (on a shared machine the others' work only slows a run down). Two baselines:
    the arm held at a start posture (the issue's), and the same reaches' own physics
    replayed through bare ``mj_step`` (every period's actuator inputs recorded, then
    stepped again from the same start, bit for bit: the loop's true ceiling, which is
    faster per step than the held arm);
(b) median / p95 solve time and accuracy of the two IK solvers on the same micro-step
    targets, and the lognormal fit of each (the IK latency model's parameters);
(c) wall time of one complete event-triggered reach (pinocchio and ikpy).

    python benchmarks/bench_core.py [--reaches 20] [--targets 200] [--repeat 3] [--json F]
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from dammrl.stack.runner import ReachRunner, ReachSettings
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.ik import DampedLeastSquaresIK, IkpyIK
from dammrl_core.state import RobotState


def raw_mj_step_rates(runner: ReachRunner, n_steps: int = 200_000) -> tuple[float, float]:
    """Steps per processor second of bare mj_step on the scene (arm posed at a start,
    PD-held): in chunks of one control period from Python, and in a single call."""
    model, data = runner.sim.model, mujoco.MjData(runner.sim.model)
    data.qpos[:6] = runner.start_posture(runner.sample(0).start)
    mujoco.mj_forward(model, data)
    start = time.process_time()
    for _ in range(n_steps // runner.substeps):
        mujoco.mj_step(model, data, nstep=runner.substeps)
    chunked = n_steps / (time.process_time() - start)
    start = time.process_time()
    mujoco.mj_step(model, data, nstep=n_steps)
    return chunked, n_steps / (time.process_time() - start)


PeriodInputs = list[tuple[np.ndarray, np.ndarray | None]]
"""Each control period's actuator controls and gains (None: the previous period's)."""


class RecordedPhysics:
    """Every episode a ticking runner's sim steps (its reset and each period's actuator
    inputs: the controls and the gains a command latches, which a reset restores), kept to
    be stepped again through bare ``mj_step``: the physics of the same reaches without the
    loop around it."""

    def __init__(self, runner: ReachRunner) -> None:
        if runner.settings.fast_forward:
            raise ValueError("record a ticking runner (fast_forward=False): one step per period")
        self.runner, sim = runner, runner.sim
        self.episodes: list[tuple[np.ndarray, tuple[float, float], Any, PeriodInputs]] = []
        self.ends: list[np.ndarray] = []  # each episode's last state (qpos, qvel)
        self._gains = sim.model.actuator_biasprm.copy()
        reset, step = sim.reset, sim.step

        def recording_reset(
            q: np.ndarray, button_xy: tuple[float, float], rng: np.random.Generator | None = None
        ) -> RobotState:
            self.episodes.append((q.copy(), button_xy, copy.deepcopy(rng), []))
            state = reset(q, button_xy, rng)
            self.ends.append(np.concatenate([sim.data.qpos, sim.data.qvel]))  # none stepped yet
            return state

        def recording_step(n_steps: int) -> None:
            inputs, gains = self.episodes[-1][3], sim.model.actuator_biasprm
            changed = not inputs or not np.array_equal(gains, self._gains)
            if changed:
                self._gains = gains.copy()
            inputs.append((sim.data.ctrl.copy(), self._gains if changed else None))
            step(n_steps)
            self.ends[-1] = np.concatenate([sim.data.qpos, sim.data.qvel])

        self._reset = reset
        sim.reset = recording_reset  # type: ignore[method-assign]
        sim.step = recording_step  # type: ignore[method-assign]

    def replay(self) -> tuple[float, int, bool]:
        """(processor seconds, physics steps, every episode ended in the state it did)."""
        sim, substeps = self.runner.sim, self.runner.substeps
        model, data = sim.model, sim.data
        spent, steps, same = 0.0, 0, True
        for (q, button_xy, rng, inputs), end in zip(self.episodes, self.ends, strict=True):
            self._reset(q, button_xy, copy.deepcopy(rng))
            start = time.process_time()
            for ctrl, gains in inputs:
                data.ctrl[:] = ctrl
                if gains is not None:
                    model.actuator_biasprm[:] = gains
                mujoco.mj_step(model, data, nstep=substeps)
            spent += time.process_time() - start
            steps += len(inputs) * substeps
            same &= bool(np.array_equal(np.concatenate([data.qpos, data.qvel]), end))
        return spent, steps, same


def replayed_rate(settings: ReachSettings, n_reaches: int) -> tuple[float, bool]:
    """(steps per processor second, replayed bit for bit) of the physics of the reaches
    ``loop_rate`` runs, through bare ``mj_step`` one control period per call."""
    runner = ReachRunner(settings.model_copy(update={"fast_forward": False}))
    recorded = RecordedPhysics(runner)
    for seed in range(n_reaches):
        runner.run(seed, (1, 1), trigger="event")
    spent, steps, same = recorded.replay()
    return steps / spent, same


def loop_rate(runner: ReachRunner, n_reaches: int) -> tuple[float, float]:
    """(physics steps per processor second, processor s per reach) of whole
    event-triggered reaches."""
    steps, start = 0, time.process_time()
    for seed in range(n_reaches):
        result = runner.run(seed, (1, 1), trigger="event")
        steps += round(result.trajectory.t[-1] / runner.sim.timestep_s)
    spent = time.process_time() - start
    return steps / spent, spent / n_reaches


def ik_targets(runner: ReachRunner, n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """(seed posture, reachable target) pairs: the posture at a sampled start, the target the
    FK of a nearby posture (micro-step sized, 1-4 cm away)."""
    rng = np.random.default_rng(seed)
    robot = runner.robot
    pairs = []
    for k in range(n):
        q = runner.start_posture(runner.sample(k).start)
        q_near = np.clip(q + rng.normal(0.0, 0.04, 6), robot.q_min + 0.03, robot.q_max - 0.03)
        pairs.append((q, runner.arm.ee_position(q_near)))
    return pairs


def bench_solver(
    solver: DampedLeastSquaresIK | IkpyIK, pairs: list[tuple[np.ndarray, np.ndarray]]
) -> dict[str, float]:
    times, errors = [], []
    for q_seed, target in pairs:
        result = solver.solve(target, q_seed)
        times.append(result.compute_s)
        errors.append(result.error_m)
    t = np.array(times)
    return {
        "median_ms": float(np.median(t) * 1e3),
        "p95_ms": float(np.percentile(t, 95) * 1e3),
        "max_error_m": float(np.max(errors)),
        "converged": float(np.mean(np.array(errors) <= 1e-4)),
        "fit_median_s": float(np.exp(np.mean(np.log(t)))),
        "fit_sigma": float(np.std(np.log(t))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reaches", type=int, default=20)
    parser.add_argument("--targets", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=3, help="each timing, the best kept")
    parser.add_argument("--json", type=Path, help="write the figures here too")
    args = parser.parse_args()

    runner = ReachRunner()
    runner.run(0)  # warm up (imports, caches)
    ticker = ReachRunner(ReachSettings(fast_forward=False))
    raw, loops, ticks, replays = [], [], [], []
    for _ in range(args.repeat):  # interleaved: the machine's load changes
        raw.append(raw_mj_step_rates(runner))
        loops.append(loop_rate(runner, args.reaches))
        ticks.append(loop_rate(ticker, args.reaches // 2))
        replays.append(replayed_rate(runner.settings, args.reaches))
    chunked, single = max(r[0] for r in raw), max(r[1] for r in raw)
    loop, ticking = max(r[0] for r in loops), max(r[0] for r in ticks)
    replayed, bitwise = max(r[0] for r in replays), all(r[1] for r in replays)
    control_hz, physics_hz = 1 / runner.control_dt_s, 1 / runner.sim.timestep_s
    print(f"(a) physics throughput (control {control_hz:.0f} Hz, physics {physics_hz:.0f} Hz)")
    print(f"    raw mj_step, one call              : {single:9.0f} steps/s")
    print(f"    raw mj_step, nstep={runner.substeps} per call      : {chunked:9.0f} steps/s")
    print(
        f"    full loop, {args.reaches} event reaches       : {loop:9.0f} steps/s  "
        f"ratio {loop / chunked:.2f} / {loop / single:.2f} (chunked / one call; goal >= 0.9)"
    )
    print(
        f"    same, ticking every period         : {ticking:9.0f} steps/s  "
        f"ratio {ticking / chunked:.2f} / {ticking / single:.2f}"
    )
    print(
        f"    the same reaches' physics replayed : {replayed:9.0f} steps/s  "
        f"loop / replayed {loop / replayed:.2f} "
        f"({'bit for bit' if bitwise else 'NOT bit for bit: the baseline is off'})"
    )

    pairs = ik_targets(runner, args.targets)
    dls = bench_solver(DampedLeastSquaresIK(runner.arm, max_step_rad=0.5), pairs)
    ikpy = bench_solver(IkpyIK(runner.arm, max_step_rad=0.5), pairs)
    print(f"(b) IK on {len(pairs)} reachable micro-step targets (same targets, same seeds)")
    for name, r in (("pinocchio DLS", dls), ("ikpy", ikpy)):
        print(
            f"    {name:14s} median {r['median_ms']:8.3f} ms  p95 {r['p95_ms']:8.3f} ms  "
            f"max error {r['max_error_m']:.1e} m ({r['converged']:.0%} <= 1e-4 m)\n"
            f"    {'':14s} lognormal fit: median {r['fit_median_s']:.5f} s, "
            f"sigma {r['fit_sigma']:.2f}"
        )
    print(
        f"    speed-up pinocchio / ikpy (median) : {ikpy['median_ms'] / dls['median_ms']:.0f}x "
        "(goal >= 100x)"
    )

    print("(c) one complete event-triggered reach (seed 7, M_1,1)")
    reach_s: dict[str, float] = {}
    for solver in ("pinocchio", "ikpy"):
        settings = ReachSettings(controller=ControllerSettings(ik_solver=solver))
        solver_runner = runner if solver == "pinocchio" else ReachRunner(settings)
        start = time.perf_counter()
        result = solver_runner.run(7, (1, 1), trigger="event")
        wall = time.perf_counter() - start
        m = result.metrics
        print(
            f"    {solver:10s}: {wall:6.3f} s wall for {m.t_total_s:.1f} s simulated "
            f"({m.t_total_s / wall:.0f}x real time), {m.n_steps} steps, {m.outcome}"
        )
        reach_s[solver] = wall
    if args.json is not None:
        figures = {
            "raw mj_step, steps/s (chunked)": chunked,
            "raw mj_step, steps/s (one call)": single,
            "loop, steps/s": loop,
            "loop / raw mj_step": loop / single,
            "ticking / raw mj_step": ticking / single,
            "replayed physics, steps/s": replayed,
            "loop / replayed physics": loop / replayed,
            "replayed bit for bit": bitwise,
            "ik pinocchio median [ms]": dls["median_ms"],
            "ik ikpy median [ms]": ikpy["median_ms"],
            "ik speed-up": ikpy["median_ms"] / dls["median_ms"],
            "reach wall [s]": reach_s,
        }
        args.json.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
