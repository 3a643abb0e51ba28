"""The real arm's tools: the emulated arm (the MuJoCo arm behind an emulated Dynamixel
chain on a pseudo-terminal), ``scan``, ``jog`` and the guided ``calibrate``.

The emulated arm is hardware as far as the robot service can tell: each servo's firmware
law (position P and D on its own frame, current limited) becomes its joint's actuator
law in MuJoCo through the arm's true calibration (ids, offsets, directions, gears, torque
constants), evaluated at every physics step; the encoders, tachometers and current
sensors report the MuJoCo joints back in servo units; the goal button's board reports
the cap's travel.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dammrl.core.dynamics import ArmModel
from dammrl.core.errors import DammrlError
from dammrl.core.robot import RobotDescription, RobotSettings
from dammrl.core.state import JointCommand
from dammrl.core.task import TaskSettings, scene_layout
from services.common.config import BusSettings
from services.robot.calibration import Calibration
from services.robot.config import ArmSettings
from services.robot.driver import DriverError, DynamixelDriver, ServoCommand
from services.robot.emulator import ServoBusEmulator
from services.robot.node import arm_limits
from services.robot.servo_chain import FAULT_HELP, ServoChain, ServoDrive, ServoReading
from services.sim.config import SimSettings
from services.sim.core import Simulation


class MujocoServos:
    """The Physics of an emulated chain: the MuJoCo arm, driven by the servos' laws."""

    def __init__(self, calibration: Calibration, robot: RobotDescription, task: TaskSettings
                 ) -> None:  # fmt: skip
        self.calibration = calibration
        self.robot = robot
        self.sim = Simulation(SimSettings(), robot, scene_layout(task))
        self.state = self.sim.reset(np.array(task.home_q_rad), (0.45, 0.0))
        self.carry_s = 0.0
        self.parked = True  # on its support until the first torque-on (a real arm is parked)
        k = np.asarray(calibration.gear_ratios) * np.asarray(calibration.torque_per_amp_nm)
        self._torque_per_amp = k  # joint torque per servo ampere (magnitude)
        self._gain_scale = k * np.asarray(calibration.gear_ratios)  # joint gain per servo gain

    def step(self, drives: dict[int, ServoDrive | None], dt_s: float) -> dict[int, ServoReading]:
        cal = self.calibration
        self.parked = self.parked and all(d is None for d in drives.values())
        if self.parked:
            return self._readings()
        goal = cal.servo_rad(self.state.q)  # an unpowered servo: no torque at all
        kp, kd, limit = np.zeros(6), np.zeros(6), np.zeros(6)
        for j, servo_id in enumerate(cal.ids):
            drive = drives.get(servo_id)
            if drive is not None:
                goal[j] = drive.goal_rad
                kp[j], kd[j] = drive.kp_a_per_rad, drive.kd_as_per_rad
                limit[j] = drive.current_limit_a
        torque_limit = np.minimum(limit * self._torque_per_amp, self.robot.tau_max)
        self.sim.model.actuator_forcerange[:6, 0] = -torque_limit
        self.sim.model.actuator_forcerange[:6, 1] = torque_limit
        zeros = np.zeros(6)
        law = JointCommand(
            cal.joint_rad(goal), zeros, zeros, kp * self._gain_scale, kd * self._gain_scale
        )
        self.sim.apply(law)
        self.carry_s += dt_s
        steps = int(self.carry_s / self.sim.timestep_s)
        if steps:
            self.carry_s -= steps * self.sim.timestep_s
            self.sim.step(steps)
            self.state = self.sim.read()
        return self._readings()

    def _readings(self) -> dict[int, ServoReading]:
        cal = self.calibration
        angle = cal.servo_rad(self.state.q)
        velocity = self.state.dq * np.asarray(cal.directions) * np.asarray(cal.gear_ratios)
        current = self.state.tau * np.asarray(cal.directions) / self._torque_per_amp
        return {
            servo_id: ServoReading(float(angle[j]), float(velocity[j]), float(current[j]))
            for j, servo_id in enumerate(cal.ids)
        }

    def button_travel_m(self) -> float:
        return float(self.state.button_travel_m)


@dataclass
class EmulatedArm:
    """The emulated arm served on ``port`` (a pty link) until closed."""

    chain: ServoChain
    physics: MujocoServos
    bus: ServoBusEmulator

    def place_button(self, xy: tuple[float, float]) -> None:
        """Put the button where the episode's goal is (what the therapist does)."""
        with self.bus.lock:
            self.physics.sim.place_button(xy)

    def follow_goals(self, settings: BusSettings, stop: threading.Event) -> None:
        """Place the button at each new episode's goal, read from the bus (a tool's
        session: it reads, it cannot command)."""
        from schemas import TaskGoal
        from services.common.bus import Bus

        with Bus(settings, "tool") as bus:
            bus.subscribe(TaskGoal)
            bus.expect(TaskGoal, "controller")
            placed = -1
            while not stop.is_set():
                goal = bus.receive(0.1)
                if isinstance(goal, TaskGoal) and goal.episode != placed:
                    self.place_button((goal.goal_m[0], goal.goal_m[1]))
                    placed = goal.episode

    def move_by_hand(self, q_rad: np.ndarray) -> None:
        """A person puts the (unpowered) arm at the joint angles ``q_rad``."""
        import mujoco

        with self.bus.lock:
            sim = self.physics.sim
            sim.data.qpos[:6] = q_rad
            sim.data.qvel[:6] = 0.0
            mujoco.mj_forward(sim.model, sim.data)
            self.physics.state = sim.read()

    def joint_speeds(self) -> np.ndarray:
        """The true joint speeds now [rad/s] (what a stop must bring to zero)."""
        with self.bus.lock:
            return np.asarray(np.abs(self.physics.state.dq))


@contextmanager
def emulated_arm(port: Path, calibration: Calibration | None = None) -> Iterator[EmulatedArm]:
    """Serve the emulated arm (its true calibration: ``calibration``) on ``port``."""
    calibration = calibration or Calibration()
    physics = MujocoServos(calibration, RobotSettings().load(), TaskSettings())
    chain = ServoChain(list(calibration.ids), physics, calibration.button_id)
    with ServoBusEmulator(chain, port) as bus:
        yield EmulatedArm(chain, physics, bus)


def inject(arm: EmulatedArm, line: str) -> str:
    """Apply one fault command (see FAULT_HELP); what was done."""
    words = line.split()
    if not words:
        return ""
    verb, argument = words[0], (int(words[1]) if len(words) > 1 and words[1].isdigit() else None)
    faults = arm.chain.faults
    with arm.bus.lock:
        if verb == "overload" and argument in arm.chain.servos:
            arm.chain.overload(argument)
        elif verb == "missing" and argument is not None:
            faults.missing.add(argument)
        elif verb == "present" and argument is not None:
            faults.missing.discard(argument)
        elif verb == "corrupt" and argument is not None:
            faults.corrupt_responses = argument
        elif verb in ("silent", "talk"):
            faults.silent = verb == "silent"
        elif verb in ("unplug", "replug"):
            faults.unplugged = verb == "unplug"
        else:
            raise DammrlError(f"unknown fault {line.strip()!r}: {FAULT_HELP}")
    return f"injected: {line.strip()}"


# ---- scan -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Device:
    servo_id: int
    model: int
    firmware: int


MODEL_NAMES = {1020: "XM430-W350", 1030: "XM430-W210", 1060: "XL430-W250", 0x4254: "button"}


def serial_ports() -> list[str]:
    """The serial devices of this machine (USB adapters first)."""
    from serial.tools import list_ports

    return sorted(p.device for p in list_ports.comports())


def scan(port: str, baud: int = 1_000_000) -> list[Device]:
    """Every device on the bus at ``port`` (a broadcast ping)."""
    import dynamixel_sdk as sdk

    handler = sdk.PortHandler(port)
    try:
        if not (handler.openPort() and handler.setBaudRate(baud)):
            raise DammrlError(f"cannot open {port} at {baud} baud")
    except OSError as exc:
        raise DammrlError(f"cannot open {port}: {exc}") from None
    try:
        found, result = sdk.PacketHandler(2.0).broadcastPing(handler)
    finally:
        handler.closePort()
    if result not in (sdk.COMM_SUCCESS, sdk.COMM_RX_TIMEOUT) and not found:
        raise DammrlError(f"ping on {port} failed (result {result})")
    return [Device(i, int(v[0]), int(v[1])) for i, v in sorted(found.items())]


# ---- jog ------------------------------------------------------------------------------
def jog(
    driver: DynamixelDriver,
    settings: ArmSettings,
    joint: int,
    by_rad: float,
    speed_rad_s: float = 0.1,
    progress: Callable[[str], None] = print,
) -> float:
    """Move one joint by ``by_rad`` (clipped to its limits), slowly, holding the others;
    the measured motion [rad] (its sign checks the joint's direction)."""
    robot = RobotSettings().load()
    limits = arm_limits(robot, driver.calibration, settings)
    arm = ArmModel(robot)
    kp, kd = np.array(settings.hold_kp_nm_per_rad), np.array(settings.hold_kd_nms_per_rad)
    period = 1.0 / settings.loop_rate_hz
    with driver:
        q0 = driver.read_state().q_rad
        target = q0.copy()
        target[joint] = float(np.clip(q0[joint] + by_rad, limits.q_min[joint], limits.q_max[joint]))
        duration = max(0.5, 1.875 * abs(target[joint] - q0[joint]) / speed_rad_s)
        progress(f"joint {robot.joint_names[joint]}: {q0[joint]:+.3f} -> {target[joint]:+.3f} rad "
                 f"in {duration:.1f} s")  # fmt: skip
        start, failures = time.monotonic(), 0
        end = start + duration + 1.0 + settings.soft_start_s  # settle, after the soft start
        while (now := time.monotonic()) < end:
            s = min(max((now - start - settings.soft_start_s) / duration, 0.0), 1.0)
            q_ref = q0 + (10 * s**3 - 15 * s**4 + 6 * s**5) * (target - q0)
            ramp = min((now - start) / max(settings.soft_start_s, 1e-9), 1.0)
            share = settings.soft_start_fraction + (1 - settings.soft_start_fraction) * ramp
            gravity = arm.inverse_dynamics(q_ref, np.zeros(6), np.zeros(6))
            law = ServoCommand(q_ref, np.zeros(6), gravity, kp * share, kd * share,
                               limits.tau_max)  # fmt: skip
            failures = _cycle(driver, law, failures, settings.max_bus_errors)
            time.sleep(period)
        moved = float(driver.read_state().q_rad[joint] - q0[joint])
    return moved


def _cycle(driver: DynamixelDriver, law: ServoCommand, failures: int, allowed: int) -> int:
    """One read and write; a failed cycle leaves the servos on their last goal, ``allowed``
    in a row end the jog (the watchdog then stops the servos)."""
    try:
        driver.read_state()
        driver.write_command(law)
    except DriverError:
        if failures + 1 >= allowed:
            raise
        return failures + 1
    return 0


# ---- calibrate --------------------------------------------------------------------------
def offsets_at_reference(servo_rad: np.ndarray, calibration: Calibration,
                         reference_q_rad: np.ndarray) -> tuple[float, ...]:  # fmt: skip
    """Zero offsets that make the servos' angles read as ``reference_q_rad``."""
    scale = np.asarray(calibration.directions) * np.asarray(calibration.gear_ratios)
    return tuple(float(v) for v in np.asarray(servo_rad) / scale - reference_q_rad)


def guided_calibration(
    port: str,
    base: Calibration,
    limits: bool,
    ask: Callable[[str], None],
    say: Callable[[str], None] = print,
) -> Calibration:
    """Directions and zero offsets (and, with ``limits``, each joint's comfortable range)
    of the arm on ``port``, moved by hand with the torque off. ``base`` gives the ids,
    gears, torque constants and the button; ``ask`` waits for the person."""
    robot = RobotSettings().load()
    identity = base.model_copy(update={"offsets_rad": (0.0,) * 6, "directions": (1,) * 6,
                                       "q_min_rad": None, "q_max_rad": None})  # fmt: skip
    driver = DynamixelDriver(port, identity)
    driver.connect(torque=False)
    try:
        read = driver.read_state  # servo angle / gear: the joint's up to direction and offset
        say("The torque is off: move the arm by hand.")
        directions = []
        for j, name in enumerate(robot.joint_names):
            ask(f"joint {j} ({name}): hold the arm still")
            before = float(read().q_rad[j])
            ask(f"move {name} about 10 deg in its positive direction, and hold")
            directions.append(direction_of(before, float(read().q_rad[j])))
        ask("put the arm in its reference posture (every joint at 0 rad) and hold")
        offsets = tuple(float(d * a) for d, a in zip(directions, read().q_rad, strict=True))
        found = base.model_copy(update={"directions": tuple(directions), "offsets_rad": offsets})
        say(f"directions {directions}, offsets {np.round(offsets, 4).tolist()} rad")
        if limits:
            found = _record_limits(found, driver, robot, ask)
    finally:
        driver.disconnect()
    return Calibration.model_validate(found.model_dump())  # checked as a whole


def _record_limits(calibration: Calibration, driver: DynamixelDriver, robot: RobotDescription,
                   ask: Callable[[str], None]) -> Calibration:  # fmt: skip
    """Each joint's comfortable range, inside the URDF's."""
    low, high = robot.q_min.copy(), robot.q_max.copy()
    for j, name in enumerate(robot.joint_names):
        ends = []
        for end in ("lower", "upper"):
            ask(f"move {name} to the {end} end of the person's comfortable range, and hold")
            q = calibration.to_rad(_ticks(driver))[j]
            ends.append(float(q))
        low[j] = max(low[j], min(ends))
        high[j] = min(high[j], max(ends))
    return calibration.model_copy(update={"q_min_rad": tuple(float(v) for v in low),
                                          "q_max_rad": tuple(float(v) for v in high)})  # fmt: skip


def _ticks(driver: DynamixelDriver) -> list[int]:
    """The servos' raw positions (through the driver's identity calibration)."""
    return driver.calibration.to_ticks(driver.read_state().q_rad)


def direction_of(before_rad: float, after_rad: float, min_motion_rad: float = 0.05) -> int:
    """+1 when the servo turned positive while the joint moved positive, else -1."""
    if abs(after_rad - before_rad) < min_motion_rad:
        raise DammrlError(
            f"the joint moved only {math.degrees(after_rad - before_rad):+.1f} deg: move it "
            f"at least {math.degrees(min_motion_rad):.0f} deg in its positive direction"
        )
    return 1 if after_rad > before_rad else -1
