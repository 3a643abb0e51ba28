"""Servo and bus faults injected while the arm moves, on each of its six joints, in
postures where gravity loads the faulted joint (prints figures): the robot service on the
emulated arm (the real driver path: dynamixel-sdk, Protocol 2.0 on a pty, the MuJoCo arm
behind the servos).

Per joint, the posture (within 0.8 rad of home, the fingertip above the table) where
gravity's torque on that joint, as a share of its effort limit, is largest among those
that leave it at least ``--room`` rad to fall before its joint limit (a fall stopped by the
limit early would hide how far it goes); shoulder yaw (joint 1) turns about the vertical,
so gravity never loads it: its posture is the one with the arm reaching furthest. The
robot service moves the joint into that posture (a homing move, 0.3 rad/s at its peak) in
the direction gravity pulls it, and each fault is injected as the joint passes 0.25
rad/s: an overload of its servo (its torque cut until a reboot), its servo overheating
(torque cut, a fault a reboot does not clear: the drive is left off, and no software
holds a joint whose drive is off), its servo missing from the bus, the whole bus silent,
the adapter unplugged (the last three recovered after 1 s). Per joint and fault, over
the 3 s after the fault: the worst excursion of that joint from where it was [rad] and
its fastest speed [rad/s], and the worst excursion of any other joint [rad]. The
overload is rebooted at two boot times of the emulated servo (a real one's was not
measured here). Each condition ``--trials`` times; the worst trial is printed.

The emulated arm runs in this process at the arm loop's priority (it stands in for the
servos' own processors, which a busy host does not slow down).

    PYTHONPATH=. python benchmarks/faults_in_motion.py [--boot 0.05 0.3] [--trials 2]
        [--joints 1 2 3 4 5 6] [--faults overheat overload missing silent unplug] [--hogs 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dammrl.devices.emulators.arm import EmulatedArm, emulated_arm, inject
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotSettings
from schemas import Header, Health, TaskGoal, encode
from services.common.runtime import prioritise
from tests.busutil import Observer, free_port, start_service, wait_for

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cpu_hogs import hogs

HOME = np.array([0.0, 1.0, 0.0, 1.6, 0.0, 0.3])
FAULTS = {
    "overload": None,
    "overheat": None,
    "missing": "present",
    "silent": "talk",
    "unplug": "replug",
}  # the fault -> what ends it after 1 s (None: nothing)
SWING_RAD = 0.4
FAULT_AT_RAD_S = 0.25  # the swing's speed when the fault comes (its peak: 0.3 rad/s)


def loaded_postures(room_rad: float, seed: int = 0, tries: int = 20_000
                    ) -> dict[int, tuple[np.ndarray, int]]:  # fmt: skip
    """Per joint: the posture where gravity loads it most with ``room_rad`` to fall, and
    the direction gravity pulls it (+1 or -1)."""
    robot = RobotSettings().load()
    arm, rng, zeros = ArmModel(robot), np.random.default_rng(seed), np.zeros(6)
    best: dict[int, tuple[float, np.ndarray, int]] = {}
    for _ in range(tries):
        q = np.clip(HOME + rng.uniform(-0.8, 0.8, 6), robot.q_min + 0.1, robot.q_max - 0.1)
        ee, _ = arm.ee_position_and_jacobian(q)
        if ee[2] < -0.15 or ee[0] < 0.2:
            continue
        holding = arm.inverse_dynamics(q, zeros, zeros)
        for j in range(6):
            pull = -1 if holding[j] > 0 else 1  # gravity turns the joint against its hold
            room = q[j] - robot.q_min[j] if pull < 0 else robot.q_max[j] - q[j]
            back = robot.q_max[j] - q[j] if pull < 0 else q[j] - robot.q_min[j]
            start = q.copy()
            start[j] -= pull * SWING_RAD
            above = arm.ee_position_and_jacobian(start)[0][2] > -0.15
            load = abs(holding[j]) / robot.tau_max[j] if j else float(np.hypot(*ee[:2]))
            fits = room >= room_rad and back > SWING_RAD + 0.1 and above
            if fits and load > best.get(j, (-1.0,))[0]:
                best[j] = (load, q, pull)
    return {j: (q, pull) for j, (_, q, pull) in best.items()}


def _goal(episode: int, q: np.ndarray) -> bytes:
    goal = TaskGoal(header=Header(stamp_ns=time.time_ns(), seq=episode, source="controller"),
                    episode=episode, seed=episode, start_m=(0.3, 0.0, 0.0), goal_m=(0.45, 0.0, 0.0),
                    q_start_rad=tuple(float(v) for v in q))  # fmt: skip
    return encode(goal)


def _true(arm: EmulatedArm) -> tuple[np.ndarray, np.ndarray]:
    with arm.bus.lock:
        return np.array(arm.physics.state.q), np.array(arm.physics.state.dq)


def run_fault(arm: EmulatedArm, joint: int, posture: np.ndarray, pull: int, fault: str
              ) -> tuple[float, float, float]:  # fmt: skip
    """One fault mid-swing: (the joint's worst excursion, its fastest speed, the others'
    worst excursion)."""
    port = free_port()
    observer = Observer(port)
    quiet = os.environ.get("DAMMRL_LOG_LEVEL", "CRITICAL")  # the table is the output
    robot = start_service("robot", port, DAMMRL_DYNAMIXEL_PORT=str(arm.bus.link),
                          DAMMRL_LOG_LEVEL=quiet)  # fmt: skip
    start = posture.copy()
    start[joint] -= pull * SWING_RAD  # the swing goes the way gravity pulls
    servo = arm.physics.calibration.ids[joint]
    try:
        wait_for(lambda: any(isinstance(h, Health) and h.service == "robot"
                             for h in observer.received), 60, "the robot")  # fmt: skip
        observer.put(TaskGoal, _goal(1, start))
        wait_for(lambda: np.abs(_true(arm)[0] - start).max() < 0.03
                 and np.abs(_true(arm)[1]).max() < 0.02, 120, "the start")  # fmt: skip
        time.sleep(0.5)
        observer.put(TaskGoal, _goal(2, posture))
        wait_for(lambda: abs(_true(arm)[1][joint]) > FAULT_AT_RAD_S, 30, "the swing")
        q0 = _true(arm)[0]
        inject(arm, f"{fault} {servo}")
        worst, fastest, others, end = 0.0, 0.0, 0.0, time.monotonic() + 3.0
        recovered = FAULTS[fault] is None
        while (now := time.monotonic()) < end:
            q, dq = _true(arm)
            worst = max(worst, abs(q[joint] - q0[joint]))
            fastest = max(fastest, abs(dq[joint]))
            rest = [k for k in range(6) if k != joint]
            others = max(others, float(np.abs(q[rest] - q0[rest]).max()))
            if not recovered and now > end - 2.0:
                inject(arm, f"{FAULTS[fault]} {servo}")
                recovered = True
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
    parser.add_argument("--trials", type=int, default=2, help="per joint and fault")
    parser.add_argument("--room", type=float, default=1.0,
                        help="the least room a posture leaves its joint to fall [rad]")  # fmt: skip
    parser.add_argument("--joints", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6],
                        help="the joints to fault (1-6)")  # fmt: skip
    parser.add_argument("--faults", nargs="+", default=None,
                        help="only: overheat overload missing silent unplug")  # fmt: skip
    parser.add_argument("--hogs", type=int, default=0,
                        help="CPU hogs (`yes > /dev/null`) beside the runs")  # fmt: skip
    args = parser.parse_args()
    prioritise(True)
    postures = loaded_postures(args.room)
    names = RobotSettings().load().joint_names
    runs = [("overheating, left off", "overheat", args.boot[0])]
    runs += [(f"overload, reboot in {b:g} s", "overload", b) for b in args.boot]
    runs += [(f"{f} 1 s", f, args.boot[0]) for f in ("missing", "silent", "unplug")]
    runs = [run for run in runs if args.faults is None or run[1] in args.faults]
    print("| joint (posture, pull) | " + " | ".join(label for label, *_ in runs) + " |")
    print("|---" * (len(runs) + 1) + "|")
    with (hogs(args.hogs), tempfile.TemporaryDirectory() as folder,
          emulated_arm(Path(folder) / "tty") as arm):  # fmt: skip
        for joint, (posture, pull) in sorted(postures.items()):
            if joint + 1 not in args.joints:
                continue
            cells = []
            for _, fault, boot in runs:
                arm.chain.boot_s = boot
                trials, failed = [], 0
                while len(trials) < args.trials and failed <= args.trials:
                    try:
                        trials.append(run_fault(arm, joint, posture, pull, fault))
                    except AssertionError as exc:  # the arm never got to the swing: no trial
                        failed += 1
                        print(f"joint {joint + 1}, {fault}: not run ({exc})", file=sys.stderr)
                if not trials:
                    cells.append("no trial")
                    continue
                worst, fastest, others = np.max(np.array(trials), axis=0)
                cells.append(f"{worst:.3f} ({fastest:.2f}), others {others:.3f}"
                             + (f" ({failed} not run)" if failed else ""))  # fmt: skip
            where = ", ".join(f"{v:.2f}" for v in posture)
            print(f"| {joint + 1} {names[joint]} ({where}; {'+' if pull > 0 else '-'}) | "
                  + " | ".join(cells) + " |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
