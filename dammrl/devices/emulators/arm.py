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

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dammrl.devices.emulators.servo_bus import ServoBusEmulator
from dammrl.devices.emulators.servo_chain import FAULT_HELP, ServoChain, ServoDrive, ServoReading
from dammrl_core.arm.dynamixel.calibration import Calibration
from dammrl_core.errors import DammrlError
from dammrl_core.robot import RobotDescription, RobotSettings
from dammrl_core.sim.settings import SimSettings
from dammrl_core.sim.simulation import Simulation
from dammrl_core.state import JointCommand
from dammrl_core.task import TaskSettings, scene_layout
from services.common.config import BusSettings
from services.common.security import OBSERVER


class MujocoServos:
    """The Physics of an emulated chain: the MuJoCo arm, driven by the servos' laws."""

    def __init__(self, calibration: Calibration, robot: RobotDescription, task: TaskSettings
                 ) -> None:  # fmt: skip
        self.calibration = calibration
        self.robot = robot
        layout = scene_layout(task)
        self.sim = Simulation(SimSettings(), robot, layout)
        self._button_travel_m = layout.button_travel_m
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
        """The cap's travel as the button's board senses it: within the cap's mechanical
        range. MuJoCo's joint limit is soft, so a cap pushed upward can rise millimetres
        past its stop (3 mm once, beside two CPU hogs after lost bus cycles), which a real
        button's stop never lets it do."""
        return min(max(float(self.state.button_travel_m), 0.0), self._button_travel_m)


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

        with Bus(settings, OBSERVER) as bus:
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
        elif verb == "overheat" and argument in arm.chain.servos:
            arm.chain.overheat(argument)
        elif verb == "missing" and argument is not None:
            faults.missing.add(argument)
        elif verb == "present" and argument is not None:
            faults.missing.discard(argument)
        elif verb == "corrupt" and argument is not None:
            faults.corrupt_responses = argument
        elif verb == "short" and argument is not None:
            faults.short_responses = argument
        elif verb == "late" and argument is not None:
            faults.late_responses = argument
        elif verb in ("silent", "talk"):
            faults.silent = verb == "silent"
        elif verb in ("unplug", "replug"):
            faults.unplugged = verb == "unplug"
        else:
            raise DammrlError(f"unknown fault {line.strip()!r}: {FAULT_HELP}")
    return f"injected: {line.strip()}"
