"""Stage S3 on the emulated arm (the real driver path: dynamixel-sdk, Protocol 2.0 on a pty,
the MuJoCo arm behind the servos), figures in one run on this machine:

(a) the bus: one read+write cycle (sync read of 7 devices, sync write of 6 goals) back to
    back in one process, against the floor of the same pty (a bare PING round trip);
(b) the robot service's loop as the servos see it: the period between goal writes, p50 /
    p99, at 100 Hz (the default) and 500 Hz; its command-to-servo latency (Health);
(c) episodes: the same seeds on the emulated chain (`dammrl up --mode real`) and in the
    sim (`dammrl up --mode virtual`): success, time, final error;
(d) faults: each injected while the arm holds: Health, largest |q_ref - q| and joint speed;
(e) the emergency stop under load (two busy processes): `dammrl stop` to confirmation and
    to every joint at rest; the watchdog: kill -9 to every servo stopped.

    PYTHONPATH=. python benchmarks/bench_robot.py [--episodes 5] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dammrl.devices.emulators.arm import EmulatedArm, emulated_arm, inject
from dammrl.devices.emulators.servo_chain import GOAL_POSITION
from dammrl_core.arm.driver import DriveCommand
from dammrl_core.arm.dynamixel.driver import DynamixelDriver
from schemas import Header, Health, RobotState, TaskGoal, encode
from tests.busutil import Observer, endpoint, free_port, start_service, wait_for

FAR_START = (0.6, 1.0, 0.0, 1.6, 0.0, 0.3)
HOME = (0.0, 1.0, 0.0, 1.6, 0.0, 0.3)


def pct(values: list[float], scale: float = 1000.0) -> str:
    p50, p99 = np.percentile(values, [50, 99]) * scale
    return f"p50 {p50:.2f}, p99 {p99:.2f}"


# ---- (a) the bus ------------------------------------------------------------------------
def bus_floor(arm: EmulatedArm, seconds: float = 3.0) -> None:
    driver = DynamixelDriver(str(arm.bus.link))
    with driver:
        state = driver.read_state()
        hold = DriveCommand(state.q_rad, np.zeros(6), np.zeros(6), np.full(6, 100.0),
                            np.full(6, 5.0), np.full(6, 10.0))  # fmt: skip
        cycles = _timed(lambda: (driver.read_state(), driver.write_command(hold)), seconds)
        port, packet = driver._port, driver._packet
        pings = _timed(lambda: packet.ping(port, 1), seconds)
    print(f"(a) read+write cycle back to back: {pct(cycles)} ms, {1 / np.mean(cycles):.0f}/s; "
          f"bare PING round trip: {pct(pings)} ms; cycle / ping = "
          f"{np.median(cycles) / np.median(pings):.1f}")  # fmt: skip


def _timed(call: Callable[[], object], seconds: float) -> list[float]:
    times, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return times


# ---- (b) the service's loop --------------------------------------------------------------
def loop_periods(arm: EmulatedArm, rate_hz: int, seconds: float = 10.0) -> None:
    """The robot service holding the arm where it is, commanded by a stand-in controller
    that answers every state (so the command-to-servo latency is measured too)."""
    port = free_port()
    observer = Observer(port)
    robot = start_service("robot", port, DAMMRL_DYNAMIXEL_PORT=str(arm.bus.link),
                          DAMMRL_ARM_LOOP_RATE_HZ=str(rate_hz))  # fmt: skip
    stop = threading.Event()
    controller = threading.Thread(target=_answer_states, args=(port, stop))
    try:
        wait_for(lambda: _health(observer, "holding"), 30, "the robot to hold")
        controller.start()
        wait_for(lambda: _health(observer, "ok"), 10, "the robot to follow commands")
        with arm.bus.lock:
            arm.chain.writes.clear()
            arm.chain.keep_writes = True
        time.sleep(seconds)
        with arm.bus.lock:
            arm.chain.keep_writes = False
            times = [t for t, address in arm.chain.writes if address == GOAL_POSITION]
        latency = _health(observer, "ok")[-1].detail.split("command to servo ")[-1]
    finally:
        stop.set()
        robot.terminate()
        robot.wait(15)
        controller.join(5)
        observer.close()
    periods = list(np.diff(times))
    print(f"(b) robot service at {rate_hz} Hz: goal writes {len(times) / seconds:.0f}/s, period "
          f"{pct(periods)} ms (emulator's clock); JointCommand stamped -> goals written: "
          f"{latency.split(',')[0]}, {latency.split(',')[1].strip()}")  # fmt: skip


def _answer_states(port: int, stop: threading.Event) -> None:
    """A stand-in controller: every state answered with a hold where the arm is."""
    from dammrl_core.dynamics import ArmModel
    from dammrl_core.robot import RobotSettings
    from schemas import JointCommand
    from services.common.bus import Bus
    from tests.busutil import client_settings

    model = ArmModel(RobotSettings().load())
    zeros = np.zeros(6)
    with Bus(client_settings(port), "controller") as bus:
        bus.subscribe(RobotState)
        publisher = bus.publisher(JointCommand)
        while not stop.is_set():
            state = bus.receive(0.1)
            if not isinstance(state, RobotState):
                continue
            q = np.array(state.q_rad)
            publisher.send(JointCommand(
                header=publisher.stamp(), episode=state.episode,
                state_stamp_ns=state.header.stamp_ns, q_ref_rad=state.q_rad,
                dq_ref_rad_s=(0.0,) * 6, tau_ff_nm=tuple(model.inverse_dynamics(q, zeros, zeros)),
                kp_nm_per_rad=(400.0, 400, 200, 200, 50, 50),
                kd_nms_per_rad=(30.0, 30, 12, 12, 1.5, 1.5),
            ))  # fmt: skip


def _health(observer: Observer, state: str, service: str = "robot") -> list[Health]:
    return [h for h in observer.of(Health) if isinstance(h, Health) and h.service == service
            and h.state == state]  # fmt: skip


# ---- (c) episodes -----------------------------------------------------------------------
def episodes(n: int) -> None:
    rows = {}
    for run in ("virtual", "virtual again", "real"):  # again: real time's own spread
        mode = run.split()[0]
        command = [sys.executable, "-m", "dammrl", "up", "--mode", mode, "--episodes", str(n),
                   "--json", "--seed", "0", "--bus-port", str(free_port())]  # fmt: skip
        if mode == "real":
            link = Path(tempfile.mkdtemp()) / "ttyROBOT"
            command += ["--robot-port", str(link), "--emulate-robot"]
        done = subprocess.run(command, capture_output=True, text=True, timeout=60 * (n + 2))
        rows[run] = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    print("(c) seed | sim: outcome, t_total s, final error mm | sim again | emulated chain")
    for sim, again, real in zip(*rows.values(), strict=False):
        cells = [f"{r['outcome']:>7} {r['t_total_s']:5.2f} {r['final_error_m'] * 1000:5.1f}"
                 for r in (sim, again, real)]  # fmt: skip
        print(f"    {sim['seed']:>4} | " + " | ".join(cells))
    for mode, results in rows.items():
        wins = sum(r["success"] for r in results)
        t = np.mean([r["t_total_s"] for r in results])
        e = np.mean([r["final_error_m"] for r in results]) * 1000
        print(f"    {mode:>13}: {wins}/{len(results)} successes, mean t_total {t:.2f} s, "
              f"mean final error {e:.1f} mm")  # fmt: skip


# ---- (d) faults -------------------------------------------------------------------------
FAULTS = [("corrupt 3", None), ("missing 3", "present 3"), ("silent", "talk"),
          ("unplug", "replug"), ("overload 6", None)]  # fmt: skip


def faults(arm: EmulatedArm) -> None:
    print(
        "(d) fault      | Health during | max |q_ref - q| rad | max joint speed rad/s "
        "(others when a servo is cut) | after recovery"
    )
    for fault, recovery in FAULTS:
        port = free_port()
        observer = Observer(port)
        robot = start_service("robot", port, DAMMRL_DYNAMIXEL_PORT=str(arm.bus.link))
        try:
            wait_for(lambda o=observer: _health(o, "holding"), 30, "the robot to hold")  # type: ignore[misc]
            time.sleep(1.5)  # the soft start is over
            seen = len(observer.received)
            q_before = arm.physics.state.q.copy()
            inject(arm, fault)
            speeds, settle = _watch(arm, 1.5, q_before)
            during = observer.received[seen:]
            states = {h.state for h in during if isinstance(h, Health) and h.service == "robot"}
            gaps = [np.abs(np.subtract(s.q_ref_applied_rad, s.q_rad)) for s in during
                    if isinstance(s, RobotState) and s.q_ref_applied_rad is not None]  # fmt: skip
            cut = [5] if fault.startswith("overload") else []
            keep = [j for j in range(6) if j not in cut]
            gap = max((float(g[keep].max()) for g in gaps), default=float("nan"))
            after = "-"
            if recovery is not None:
                inject(arm, recovery)
                mark = len(observer.received)
                wait_for(lambda o=observer, n=mark: _holds_since(o, n), 10, "recovery")  # type: ignore[misc]
                after = "holding again"
            print(f"    {fault:<11} | {'/'.join(sorted(states)):<13} | {gap:18.4f} | "
                  f"{speeds[:, keep].max():.3f} | {settle[keep].max():.4f} | {after}")  # fmt: skip
        finally:
            robot.terminate()
            robot.wait(15)
            observer.close()
            if fault.startswith("overload"):
                _clear_overload(arm)


def _holds_since(observer: Observer, mark: int) -> bool:
    return any(isinstance(h, Health) and h.state == "holding" for h in observer.received[mark:])


def _watch(arm: EmulatedArm, seconds: float, q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint speeds while it runs, and how far each joint went from ``q0``."""
    rows, moved, end = [], np.zeros(6), time.monotonic() + seconds
    while time.monotonic() < end:
        rows.append(arm.joint_speeds())
        moved = np.maximum(moved, np.abs(arm.physics.state.q - q0))
        time.sleep(0.005)
    return np.array(rows), moved


def _clear_overload(arm: EmulatedArm) -> None:
    """What a power cycle does to the emulated servos' latched errors."""
    with arm.bus.lock:
        for servo in arm.chain.motors.values():
            servo.table[70] = 0


# ---- (e) the stop and the watchdog -------------------------------------------------------
def _burn(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


def _move(arm: EmulatedArm, observer: Observer, q_start: tuple[float, ...], episode: int) -> None:
    goal = TaskGoal(header=Header(stamp_ns=time.time_ns(), seq=episode, source="controller"),
                    episode=episode, seed=1, start_m=(0.3, 0.0, 0.0), goal_m=(0.45, 0.0, 0.0),
                    q_start_rad=q_start)  # fmt: skip
    observer.put(TaskGoal, encode(goal))
    wait_for(lambda: arm.joint_speeds().max() > 0.15, 15, "the arm to move")


def _rest(arm: EmulatedArm, since: float, speed: float = 0.02) -> float:
    wait_for(lambda: arm.joint_speeds().max() < speed, 10, "rest")
    return time.monotonic() - since


def stops(arm: EmulatedArm, repeats: int) -> None:
    """`dammrl stop` as a new process, and the stop console (a session already open)."""
    from dammrl.stack.stop import StopConsole
    from tests.busutil import client_settings

    port = free_port()
    observer = Observer(port)
    robot = start_service("robot", port, DAMMRL_DYNAMIXEL_PORT=str(arm.bus.link))
    context = multiprocessing.get_context("spawn")
    load = [context.Process(target=_burn, args=(3600,), daemon=True) for _ in range(2)]
    command = [sys.executable, "-m", "dammrl", "stop", "--connect", endpoint(port)]
    figures: dict[str, tuple[list[float], list[float]]] = {"cli": ([], []), "console": ([], [])}
    episode = 0
    try:
        wait_for(lambda: _health(observer, "holding"), 30, "the robot to hold")
        console = StopConsole(client_settings(port))
        for process in load:
            process.start()
        for i in range(2 * repeats):
            episode += 1
            _move(arm, observer, FAR_START if i % 2 == 0 else HOME, episode)
            started = time.monotonic()
            if i < repeats:
                done = subprocess.run(command, capture_output=True, text=True, timeout=60)
                confirmed = float(done.stdout.split("after ")[1].split(" ms")[0]) / 1000
                way = "cli"
            else:
                confirmed, way = console.send(True).acknowledged["robot"], "console"
            figures[way][0].append(confirmed)
            figures[way][1].append(_rest(arm, started))
            console.send(False)
            wait_for(lambda: arm.joint_speeds().max() < 0.02, 10, "rest")
        console.close()
    finally:
        for process in load:
            process.terminate()
        robot.terminate()
        robot.wait(15)
        observer.close()
    for way, (confirmed_s, rest_s) in figures.items():
        start = "`dammrl stop` started" if way == "cli" else "console's stop sent"
        print(f"(e) under load, {repeats} stops while moving, {way}: published -> robot "
              f"confirmed {pct(confirmed_s)} ms; {start} -> every joint < 0.02 rad/s "
              f"{pct(rest_s)} ms")  # fmt: skip


def watchdog(arm: EmulatedArm, repeats: int) -> None:
    expired, rested = [], []
    for _ in range(repeats):
        port = free_port()
        observer = Observer(port)
        robot = start_service("robot", port, DAMMRL_DYNAMIXEL_PORT=str(arm.bus.link))
        try:
            wait_for(lambda o=observer: _health(o, "holding"), 30, "hold")  # type: ignore[misc]
            time.sleep(1.2)
            q = arm.physics.state.q
            target = FAR_START if abs(q[0] - FAR_START[0]) > 0.3 else HOME
            _move(arm, observer, target, 1)
            robot.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            motors = list(arm.chain.motors.values())
            wait_for(lambda m=motors: all(s.watchdog_expired for s in m), 2, "watchdog")  # type: ignore[misc]
            expired.append(time.monotonic() - killed)
            rested.append(_rest(arm, killed, 0.05))
        finally:
            robot.kill()
            robot.wait(10)
            observer.close()
    print(
        f"(e) kill -9 while moving, watchdog 0.1 s, {repeats} times: every servo's watchdog "
        f"expired after {pct(expired)} ms; every joint < 0.05 rad/s after {pct(rested)} ms"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder, emulated_arm(Path(folder) / "tty") as arm:
        bus_floor(arm)
        for rate in (100, 500):
            loop_periods(arm, rate)
        faults(arm)
        watchdog(arm, args.repeats)
        stops(arm, args.repeats)
    episodes(args.episodes)
    threading.Event().wait(0)


if __name__ == "__main__":
    main()
