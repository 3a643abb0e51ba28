"""The simulation node: MuJoCo in real time on the bus.

Each state period it takes up the latest valid JointCommand, steps the physics (the
impedance law runs at physics rate inside MuJoCo) and publishes the RobotState. A
command that breaks the joint, effort or gain limits is rejected; when no valid command
arrived for ``command_stale_s`` the arm holds where it is (gravity compensation plus
damping). A TaskGoal resets the arm to its start posture and moves the button to its goal.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Sequence

import numpy as np

from dammrl.robot import RobotDescription
from dammrl.robot.scene import SceneLayout
from dammrl.state import JointCommand as CoreCommand
from dammrl.task import TaskSettings
from schemas import JointCommand, RobotState, TaskGoal
from services.common import convert
from services.common.bus import Bus
from services.common.entry import run_service
from services.common.runtime import Pacer
from services.controller.dynamics import ArmModel
from services.sim.config import SimSettings
from services.sim.core import Simulation

log = logging.getLogger("dammrl.sim")


def command_violation(
    command: JointCommand, robot: RobotDescription, settings: SimSettings
) -> str | None:
    """Why a command must not reach the arm, or None."""
    q_ref = np.array(command.q_ref_rad)
    tolerance = settings.limit_tolerance_rad
    outside = (q_ref < robot.q_min - tolerance) | (q_ref > robot.q_max + tolerance)
    if outside.any():
        i = int(np.argmax(outside))
        return (
            f"q_ref of {robot.joint_names[i]} = {q_ref[i]:.3f} rad outside "
            f"[{robot.q_min[i]:.3f}, {robot.q_max[i]:.3f}] rad"
        )
    tau = np.abs(np.array(command.tau_ff_nm))
    if (tau > robot.tau_max).any():
        i = int(np.argmax(tau - robot.tau_max))
        name, limit = robot.joint_names[i], robot.tau_max[i]
        return f"tau_ff of {name} = {tau[i]:.1f} N m beyond its effort limit {limit:.1f} N m"
    kp, kd = max(command.kp_nm_per_rad), max(command.kd_nms_per_rad)
    if kp > settings.max_kp_nm_per_rad:
        return f"kp {kp:.0f} N m/rad above the allowed {settings.max_kp_nm_per_rad:.0f}"
    if kd > settings.max_kd_nms_per_rad:
        return f"kd {kd:.0f} N m s/rad above the allowed {settings.max_kd_nms_per_rad:.0f}"
    return None


def goal_violation(
    goal: TaskGoal, robot: RobotDescription, layout: SceneLayout, settings: SimSettings
) -> str | None:
    """Why a TaskGoal must not reset the arm, or None."""
    q = np.array(goal.q_start_rad)
    if not robot.within_limits(q, settings.limit_tolerance_rad):
        return f"start posture {np.round(q, 3).tolist()} rad outside the joint limits"
    (cx, cy), (hx, hy) = layout.table_center_xy_m, layout.table_half_size_xy_m
    x, y = goal.goal_m[0], goal.goal_m[1]
    if abs(x - cx) > hx or abs(y - cy) > hy:
        return f"button position ({x:.3f}, {y:.3f}) m is not on the table"
    return None


class SimNode:
    def __init__(self, settings: SimSettings, task: TaskSettings, bus: Bus) -> None:
        self.settings = settings
        self.bus = bus
        self.sim = Simulation(settings, seed=settings.seed)
        self.arm = ArmModel(self.sim.robot)
        self.substeps = max(1, round(1.0 / (settings.state_rate_hz * self.sim.timestep_s)))
        self.episode = 0
        self.command: CoreCommand | None = None
        self.command_wall_s = 0.0
        self.holding = False
        self.round_trips_s: deque[float] = deque(maxlen=100_000)  # state sent -> command in
        self.pacer = Pacer(self.substeps * self.sim.timestep_s)
        self.state_publisher = bus.publisher(RobotState)
        bus.subscribe(JointCommand, TaskGoal)
        bus.expect(JointCommand, "controller")
        bus.expect(TaskGoal, "controller")
        state = self.sim.reset(np.array(task.home_q_rad), (0.45, 0.0))
        self._hold(state.q)

    def run(self, stop: threading.Event) -> None:
        pacer = self.pacer
        pacer.restart()
        log.info(
            "simulating at %.0f Hz state rate, %d physics steps per period",
            1 / pacer.period_s,
            self.substeps,
        )
        while not stop.is_set():
            self._take_messages()
            self._hold_if_stale()
            self.sim.step(self.substeps)
            state = self.sim.read()
            self.state_publisher.publish(**convert.state_fields(state, self.episode, self.holding))
            detail = f"missed {pacer.missed} of {pacer.ticks} deadlines"
            self.bus.report_health("holding" if self.holding else "ok", detail)
            pacer.wait()

    def _take_messages(self) -> None:
        while (message := self.bus.receive(0)) is not None:
            if isinstance(message, TaskGoal):
                self._reset(message)
            elif isinstance(message, JointCommand) and message.episode == self.episode:
                self._take_command(message)

    def _take_command(self, message: JointCommand) -> None:
        reason = command_violation(message, self.sim.robot, self.settings)
        if reason is not None:
            self.bus.reject(self.bus.key(JointCommand), reason)
            return
        self.command = convert.joint_command(message)
        self.command_wall_s = time.monotonic()
        self.round_trips_s.append((self.bus.arrival_ns - message.state_stamp_ns) * 1e-9)
        self.sim.apply(self.command)
        if self.holding:
            log.info("commands resumed: leaving the hold")
        self.holding = False

    def _hold_if_stale(self) -> None:
        if self.holding or time.monotonic() - self.command_wall_s <= self.settings.command_stale_s:
            return
        log.warning("no valid command for %.2f s: holding position", self.settings.command_stale_s)
        self._hold(self.sim.read().q)

    def _hold(self, q: np.ndarray) -> None:
        """Gravity compensation at ``q``, with the last command's gains (the stiffness the
        arm had) or, before any command, the hold gains of the settings."""
        zeros = np.zeros(6)
        last = self.command
        kp = last.kp if last is not None else np.full(6, self.settings.hold_kp_nm_per_rad)
        kd = last.kd if last is not None else np.full(6, self.settings.hold_kd_nms_per_rad)
        self.sim.apply(
            CoreCommand(
                q_ref=q.copy(),
                dq_ref=zeros,
                tau_ff=self.arm.inverse_dynamics(q, zeros, zeros),
                kp=kp,
                kd=kd,
            )
        )
        self.holding = True

    def _reset(self, goal: TaskGoal) -> None:
        if goal.episode == self.episode:
            return  # a repeated announcement
        reason = goal_violation(goal, self.sim.robot, self.sim.layout, self.settings)
        if reason is not None:
            self.bus.reject(self.bus.key(TaskGoal), reason)
            return
        self.episode = goal.episode
        state = self.sim.reset(np.array(goal.q_start_rad), (goal.goal_m[0], goal.goal_m[1]))
        self.command = None
        self._hold(state.q)
        log.info("episode %d: arm at its start, button at %s", goal.episode, goal.goal_m)


def main(argv: Sequence[str] | None = None) -> int:
    """Simulation service: the MuJoCo arm in real time on the bus."""
    return run_service(
        "sim",
        "Simulation service: the MuJoCo arm in real time on the bus.",
        "DAMMRL_SIM_*, DAMMRL_TASK_*",
        lambda bus, _: SimNode(SimSettings(), TaskSettings(), bus),
        argv,
    )
