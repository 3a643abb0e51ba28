"""Servo and bus faults injected while the arm moves, in postures where gravity loads the
faulted joint (prints figures): the robot service on the emulated arm (the real driver
path: dynamixel-sdk, Protocol 2.0 on a pty, the MuJoCo arm behind the servos).

For each joint 2-6 (joint 1, shoulder yaw, turns about the vertical: gravity never loads
it) a posture within 0.8 rad of home where gravity loads that joint most (a seeded search,
the fingertip above the table) is the goal of a homing move that swings the joint by
0.4 rad; each fault is injected as the joint passes 0.1 rad/s: an overload of its servo
(torque cut until a reboot), its servo missing from the bus, the whole bus silent, the
adapter unplugged (the last three recovered after 1 s). Per joint and fault: the worst
excursion of that joint from where it was at the fault [rad], its fastest speed [rad/s],
and the other joints' worst excursion, over 3 s. The overload is run with no reboot
(``DAMMRL_ARM_MAX_RESTARTS=0``: what the service did before) and with the reboot, at two
boot times of the emulated servo (a real one's was not measured here).

    PYTHONPATH=. python benchmarks/faults_in_motion.py [--boot 0.05 0.3]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from dammrl.emulators.arm import EmulatedArm, emulated_arm, inject
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotSettings
from schemas import Header, Health, TaskGoal, encode
from tests.busutil import Observer, free_port, start_service, wait_for

HOME = np.array([0.0, 1.0, 0.0, 1.6, 0.0, 0.3])
FAULTS = {"overload": None, "missing": "present", "silent": "talk", "unplug": "replug"}
SWING_RAD = 0.4


def loaded_postures(seed: int = 0, tries: int = 20_000) -> dict[int, np.ndarray]:
    """Per joint 1-5: the posture within 0.8 rad of home where gravity's torque on that
    joint, as a share of its effort limit, is largest (the fingertip above the table)."""
    robot = RobotSettings().load()
    arm, rng, zeros = ArmModel(robot), np.random.default_rng(seed), np.zeros(6)
    best: dict[int, tuple[float, np.ndarray]] = {}
    for _ in range(tries):
        q = np.clip(HOME + rng.uniform(-0.8, 0.8, 6), robot.q_min + 0.1, robot.q_max - 0.1)
        ee, _ = arm.ee_position_and_jacobian(q)
        if ee[2] < -0.15 or ee[0] < 0.2:
            continue
        load = np.abs(arm.inverse_dynamics(q, zeros, zeros)) / robot.tau_max
        for j in range(1, 6):
            if load[j] > best.get(j, (0.0, q))[0]:
                best[j] = (float(load[j]), q)
    return {j: q for j, (_, q) in best.items()}


def _goal(episode: int, q: np.ndarray) -> bytes:
    goal = TaskGoal(header=Header(stamp_ns=time.time_ns(), seq=episode, source="controller"),
                    episode=episode, seed=episode, start_m=(0.3, 0.0, 0.0), goal_m=(0.45, 0.0, 0.0),
                    q_start_rad=tuple(float(v) for v in q))  # fmt: skip
    return encode(goal)


def _true(arm: EmulatedArm) -> tuple[np.ndarray, np.ndarray]:
    with arm.bus.lock:
        return np.array(arm.physics.state.q), np.array(arm.physics.state.dq)


def run_fault(arm: EmulatedArm, joint: int, posture: np.ndarray, fault: str,
              reboots: int) -> tuple[float, float, float]:  # fmt: skip
    port = free_port()
    observer = Observer(port)
    robot = start_service("robot", port, DAMMRL_DYNAMIXEL_PORT=str(arm.bus.link),
                          DAMMRL_ARM_MAX_RESTARTS=str(reboots),
                          DAMMRL_LOG_LEVEL="ERROR")  # fmt: skip
    start = posture.copy()
    start[joint] -= SWING_RAD
    try:
        wait_for(lambda: any(isinstance(h, Health) and h.service == "robot"
                             for h in observer.received), 30, "the robot")  # fmt: skip
        observer.put(TaskGoal, _goal(1, start))
        wait_for(lambda: np.abs(_true(arm)[0] - start).max() < 0.03
                 and np.abs(_true(arm)[1]).max() < 0.02, 30, "the start")  # fmt: skip
        time.sleep(0.5)
        observer.put(TaskGoal, _goal(2, posture))
        wait_for(lambda: abs(_true(arm)[1][joint]) > 0.1, 15, "the swing")
        q0 = _true(arm)[0]
        inject(arm, f"{fault} {arm.physics.calibration.ids[joint]}")
        worst, fastest, others, end = 0.0, 0.0, 0.0, time.monotonic() + 3.0
        while (now := time.monotonic()) < end:
            q, dq = _true(arm)
            worst = max(worst, abs(q[joint] - q0[joint]))
            fastest = max(fastest, abs(dq[joint]))
            rest = [k for k in range(6) if k != joint]
            others = max(others, float(np.abs(q[rest] - q0[rest]).max()))
            if FAULTS[fault] is not None and now > end - 2.0:
                inject(arm, f"{FAULTS[fault]} {arm.physics.calibration.ids[joint]}")
            time.sleep(0.005)
    finally:
        robot.terminate()
        robot.wait(15)
        observer.close()
        _power_cycle(arm)
    return worst, fastest, others


def _power_cycle(arm: EmulatedArm) -> None:
    """What switching the servos off and on does: errors and boots cleared, all present."""
    with arm.bus.lock:
        faults = arm.chain.faults
        faults.missing.clear()
        faults.silent = faults.unplugged = False
        for servo in arm.chain.motors.values():
            servo.booting_until_s = None
            servo.table[70] = 0  # hardware error status


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--boot", type=float, nargs="+", default=[0.05, 0.3],
                        help="boot times of the emulated servo after a reboot [s]")  # fmt: skip
    args = parser.parse_args()
    postures = loaded_postures()
    names = RobotSettings().load().joint_names
    runs = [("overload, no reboot (before)", "overload", 0, args.boot[0])]
    runs += [(f"overload, reboot, boot {b:g} s", "overload", 2, b) for b in args.boot]
    runs += [(f"{f} (recovered after 1 s)", f, 2, args.boot[0]) for f in ("missing", "silent",
                                                                           "unplug")]  # fmt: skip
    print(
        "joint | fault | worst excursion of the joint [rad] | its fastest [rad/s] | "
        "others' worst excursion [rad]"
    )
    with tempfile.TemporaryDirectory() as folder, emulated_arm(Path(folder) / "tty") as arm:
        for joint, posture in sorted(postures.items()):
            for label, fault, reboots, boot in runs:
                arm.chain.boot_s = boot
                worst, fastest, others = run_fault(arm, joint, posture, fault, reboots)
                print(
                    f"{joint + 1} {names[joint]:<15} | {label:<30} | {worst:.3f} | "
                    f"{fastest:.2f} | {others:.3f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
