"""How far the stack's own controller stays from the arm's caps (prints figures).

Runs reaches in-process with every M_ij corner, both triggers, nominal and randomised
arms, and records at every command the largest |q_ref - q|, |dq_ref| / velocity limit
and change of q_ref between commands: the margins that justify the arm-side caps
(DAMMRL_SIM_MAX_RELATIVE_TARGET_RAD, DAMMRL_SIM_REFERENCE_SPEED_FRACTION).

    python benchmarks/arm_caps_margin.py [--seeds 10]
"""

from __future__ import annotations

import argparse

import numpy as np

from dammrl.stack.runner import ReachRunner, ReachSettings
from dammrl_core.sim.settings import DomainRandomization, SimSettings
from dammrl_core.sim.simulation import Simulation
from dammrl_core.state import JointCommand


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    worst = {"relative": 0.0, "speed": 0.0, "rate": 0.0}
    original = Simulation.apply
    last: dict[str, np.ndarray] = {}

    def apply(sim: Simulation, command: JointCommand) -> None:
        q = sim.data.qpos[:6]
        worst["relative"] = max(worst["relative"], float(np.max(np.abs(command.q_ref - q))))
        speed = float(np.max(np.abs(command.dq_ref) / sim.robot.dq_max))
        worst["speed"] = max(worst["speed"], speed)
        if "q_ref" in last:
            step = float(np.max(np.abs(command.q_ref - last["q_ref"])))
            worst["rate"] = max(worst["rate"], step)
        last["q_ref"] = command.q_ref.copy()
        original(sim, command)

    Simulation.apply = apply  # type: ignore[method-assign]
    reaches = 0
    for randomize in (False, True):
        sim = SimSettings(randomization=DomainRandomization(enabled=randomize))
        runner = ReachRunner(ReachSettings(sim=sim))
        for trigger in ("event", "fixed"):
            for model in ((2, 1), (1, 8), (1, 1), (2, 8)):
                for seed in range(7_000_400, 7_000_400 + args.seeds):
                    last.clear()
                    runner.run(seed, model=model, trigger=trigger)
                    reaches += 1
    print(f"{reaches} reaches (both triggers, M_1,1 M_2,1 M_1,8 M_2,8, nominal and randomised)")
    print(f"largest |q_ref - q|                 : {worst['relative']:.4f} rad (cap 0.15)")
    print(f"largest |dq_ref| / velocity limit   : {worst['speed']:.3f} (cap 1.0)")
    print(f"largest q_ref change per command    : {worst['rate']:.4f} rad per 10 ms")


if __name__ == "__main__":
    main()
