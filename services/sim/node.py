"""The simulation node: MuJoCo on the bus, in real time or in lockstep with the controller.

Each state period it publishes the RobotState, takes up the latest valid JointCommand
and steps the physics (the impedance law runs at physics rate inside MuJoCo). In real
time the period is paced by the wall clock; in lockstep (``DAMMRL_BUS_LOCKSTEP``) the
next step waits for the controller's answer to the published state. A command that
breaks the joint, effort or gain limits is rejected; when no valid command arrived for
``command_stale_s`` (lockstep: no answer in time) the arm holds where it is (gravity
compensation plus damping). A TaskGoal resets the arm to its start posture, reseeds its
randomisation with the episode's seed and moves the button to the goal; the reset state
is the first state of the episode.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Sequence

import numpy as np

from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotSettings
from dammrl_core.safety import (
    ArmCaps,
    CommandFreshness,
    LimitMonitor,
    StopLatch,
    goal_violation,
    guard_command,
)
from dammrl_core.sim.settings import SimSettings
from dammrl_core.sim.simulation import Simulation
from dammrl_core.state import JointCommand as CoreCommand
from dammrl_core.task import TaskSettings, scene_layout, seed_streams
from schemas import (
    EmergencyStop,
    GoalRefused,
    Header,
    JointCommand,
    RobotState,
    TaskGoal,
    decode,
    encode,
)
from services.common import convert
from services.common.bus import Bus
from services.common.entry import run_service
from services.common.runtime import Pacer
from services.common.security import OPERATOR

log = logging.getLogger("dammrl.sim")


class SimNode:
    def __init__(
        self, settings: SimSettings, task: TaskSettings, robot: RobotSettings, bus: Bus
    ) -> None:
        self.settings = settings
        self.bus = bus
        self.sim = Simulation(settings, robot.load(), scene_layout(task))
        self.arm = ArmModel(self.sim.robot)
        self.substeps = max(1, round(1.0 / (settings.state_rate_hz * self.sim.timestep_s)))
        self.episode = 0
        self.command: CoreCommand | None = None
        self.command_message: JointCommand | None = None  # the last one applied, as it came
        self.command_wall_s = 0.0
        self.answered = False  # lockstep: the controller answered the last state
        self.reset_pending = False  # a TaskGoal reset the arm: publish its state first
        self.settling = False  # a reset was refused while the arm moved
        self.holding = False
        self.round_trips_s: deque[float] = deque(maxlen=100_000)  # state sent -> command in
        # periods stepped under the controller's command, and those of them stepped on the
        # command answering the state published at their start (the loop closed in time)
        self.commanded_periods = 0
        self.answered_periods = 0
        self.pacer = Pacer(self.substeps * self.sim.timestep_s)
        self.state_publisher = bus.publisher(RobotState)
        self.refusals = bus.publisher(GoalRefused)
        self.caps = ArmCaps(
            settings.limit_tolerance_rad, settings.max_kp_nm_per_rad, settings.max_kd_nms_per_rad,
            settings.max_relative_target_rad, settings.reference_speed_fraction,
        )  # fmt: skip
        answerable = max(1, round(settings.command_max_age_s * settings.state_rate_hz))
        self.freshness = CommandFreshness(answerable)
        self.stop_latch = StopLatch()
        self.fault: str | None = None  # the arm beyond a limit or its speed: latched
        self.monitor = LimitMonitor(
            self.sim.robot, settings.limit_tolerance_rad, settings.overspeed_stop_fraction
        )
        self.reported_stopped = False
        self.in_force_answers_ns: int | None = None  # ... while that command is in force
        self.last_stamp_ns = -1
        bus.subscribe(JointCommand, TaskGoal, EmergencyStop)
        bus.expect(JointCommand, "controller")
        bus.expect(TaskGoal, "controller")
        bus.expect(EmergencyStop, OPERATOR)  # `dammrl stop` (the operator)
        state = self.sim.reset(np.array(task.home_q_rad), (0.45, 0.0))
        self._hold(state.q)
        self.state = state

    def run(self, stop: threading.Event) -> None:
        lockstep = self.bus.settings.lockstep
        self.pacer.restart()
        log.info(
            "simulating %s at %.0f Hz state rate, %d physics steps per period",
            "in lockstep" if lockstep else "in real time",
            1 / self.pacer.period_s,
            self.substeps,
        )
        while not stop.is_set():
            self._publish_state()
            if lockstep and not self.settling:
                self._await_answer()
            else:  # real time, or lockstep while the arm settles for a refused reset
                # each command is taken as it arrives (its round trip is true), applied at
                # the deadline's step as before: the physics sees what it saw
                self.pacer.wait(self._take_messages)
                self._take_messages(0)
            if self.reset_pending:
                continue  # the reset state is published before any step
            self._hold_if_stale(lockstep)
            self._count_period()
            self.sim.step_governed(self.substeps)
            self.state = self.sim.read()
            self._check_limits()

    def _publish_state(self) -> None:
        self.reset_pending = False
        message = self.state_publisher.send(
            convert.state_message(
                self.state_publisher.stamp(),
                self.state,
                self.episode,
                self.holding,
                None if self.sim.applied is None else self.sim.applied.q_ref,
                self.in_force_answers_ns,
            )
        )
        self.last_stamp_ns = message.header.stamp_ns
        self.freshness.published(self.last_stamp_ns, self.state.t_s)
        if not self.bus.settings.lockstep:  # in lockstep the loop never waits for long
            self.bus.rehearse(self.pacer.next_s + self.pacer.period_s, self._rehearse)
        self.answered = False
        answered = self.answered_periods / max(self.commanded_periods, 1)
        detail = (
            f"missed {self.pacer.missed} of {self.pacer.ticks} deadlines, "
            f"{answered:.1%} of commanded periods on their own state's answer, "
            f"{self.freshness.clamped} commands clamped"
        )
        reason = self.stop_latch.reason or self.fault
        stopped = reason is not None
        changed, self.reported_stopped = stopped != self.reported_stopped, stopped
        if stopped:
            self.bus.report_health("stopped", f"{reason}; {detail}", changed)
        else:
            self.bus.report_health("holding" if self.holding else "ok", detail, changed)

    def _rehearse(self) -> None:
        """The next period's messages rehearsed on the last ones (``Bus.rehearse``): the
        state built and encoded, the command decoded and checked; nothing sent or kept."""
        applied = None if self.sim.applied is None else self.sim.applied.q_ref
        header = Header(stamp_ns=time.time_ns(), seq=0, source=self.bus.source)
        encode(convert.state_message(header, self.state, self.episode, self.holding, applied,
                                     self.in_force_answers_ns))  # fmt: skip
        message = self.command_message
        if message is not None:
            command = convert.joint_command(decode(JointCommand, encode(message)))
            guard_command(command, self.state.q, applied, 2 * self.pacer.period_s,
                          self.sim.robot, self.caps)  # fmt: skip

    def _count_period(self) -> None:
        """A period about to be stepped: under command, and on its own state's answer?"""
        if not self.holding:
            self.commanded_periods += 1
            self.answered_periods += self.in_force_answers_ns == self.last_stamp_ns

    def _await_answer(self) -> None:
        """Lockstep: take messages until the command answering the last state (bounded)."""
        deadline = time.monotonic() + self.bus.settings.lockstep_timeout_s
        while not (self.answered or self.reset_pending):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            self._take_messages(remaining)

    def _take_messages(self, timeout_s: float) -> None:
        """Dispatch what has arrived (waiting up to ``timeout_s`` for the first)."""
        for message in self.bus.receive_all(timeout_s):
            if isinstance(message, EmergencyStop):
                self._take_stop(message)
            elif isinstance(message, TaskGoal):
                self._reset(message)
            elif isinstance(message, JointCommand) and message.episode == self.episode:
                self._take_command(message)

    def _take_stop(self, message: EmergencyStop) -> None:
        """Stop: hold where the arm is with the hold gains (low: a person can move it) and
        take no command until released; a release leaves the arm holding."""
        if not self.stop_latch.take(message.engaged, message.header.source, message.reason):
            return
        if self.stop_latch.engaged:
            log.warning("%s: holding", self.stop_latch.reason)
            self.command = None  # the stop's gains are the hold gains, not the last command's
            self._hold(self.state.q)
        else:
            log.warning("emergency stop released by %s: holding until commands resume",
                        message.header.source)  # fmt: skip

    def _check_limits(self) -> None:
        """Latch a fault when a joint is beyond its limits or its speed (the robot service's
        rule): hold where the arm is with the hold gains, take nothing until a restart."""
        if self.fault is not None:
            return
        reason = self.monitor.check(self.state.q, self.state.dq)
        if reason is None:
            return
        self.fault = f"arm fault: {reason}"
        log.error("%s: stopping until the service restarts", self.fault)
        self.command = None
        self._hold(self.state.q)

    def _take_command(self, message: JointCommand) -> None:
        blocked = self.stop_latch.reason or self.fault
        if blocked is not None:
            self.bus.reject(self.bus.key(JointCommand), blocked)
            return
        reason = self.freshness.why_stale(message.state_stamp_ns)
        applied = self.sim.applied  # the reference in force, a hold's included
        guarded = guard_command(
            convert.joint_command(message),
            self.state.q,
            None if applied is None else applied.q_ref,
            self.freshness.allowance_s(message.state_stamp_ns, 2 * self.pacer.period_s),
            self.sim.robot,
            self.caps,
        )
        reason = reason or (None if guarded.clamped else guarded.reason)
        if reason is not None or guarded.command is None:
            self.bus.reject(self.bus.key(JointCommand), reason or "rejected")
            return
        if guarded.clamped and (
            line := self.freshness.clamp(guarded.reason, message.state_stamp_ns)
        ):
            log.log(guarded.log_level, "%s", line)
        self.command, self.command_message = guarded.command, message
        self.freshness.applied(message.state_stamp_ns)
        self.in_force_answers_ns = message.state_stamp_ns
        self.command_wall_s = time.monotonic()
        self.answered |= message.state_stamp_ns == self.last_stamp_ns
        self.round_trips_s.append((self.bus.arrival_ns - message.state_stamp_ns) * 1e-9)
        self.sim.apply(self.command)
        if self.holding:
            log.info("commands resumed: leaving the hold")
        self.holding = False

    def _hold_if_stale(self, lockstep: bool) -> None:
        if lockstep:
            stale = not self.answered
        else:
            stale = time.monotonic() - self.command_wall_s > self.settings.command_stale_s
        if self.holding or not stale:
            return
        if self.settling:  # the episode ended and the next one waits for the arm to rest
            log.info("between episodes: holding position until the arm rests")
        else:
            who = "alive but silent" if "controller" in self.bus.alive_peers() else "gone"
            log.warning("no valid command from the controller (%s) for %.2f s: holding "
                        "position", who, self.settings.command_stale_s)  # fmt: skip
        self._hold(self.state.q)

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
        self.freshness.held(self.sim.t_s)
        self.in_force_answers_ns = None
        self.holding = True

    def _reset(self, goal: TaskGoal) -> None:
        if goal.episode == self.episode:
            return  # a repeated announcement
        blocked = self.stop_latch.reason or self.fault
        if blocked is not None:
            self.bus.reject(self.bus.key(TaskGoal), blocked)
            return
        q_start = np.array(goal.q_start_rad)
        reason = goal_violation(
            q_start, goal.goal_m, self.sim.robot, self.sim.layout, self.settings.limit_tolerance_rad
        )
        speed = float(np.max(np.abs(self.state.dq)))
        if reason is None and speed > self.settings.rest_speed_rad_s:
            # the last reach just ended: expected, not bad input (the controller announces
            # the goal again until the arm rests and the reset takes it)
            if not self.settling:
                log.info("episode %d waits until the arm rests (%.2f rad/s)", goal.episode, speed)
            self.settling = True  # lockstep: step on without waiting, so it comes to rest
            return
        if reason is not None:  # this arm can never begin it: the controller goes on
            self.bus.reject(self.bus.key(TaskGoal), reason)
            self.refusals.send(convert.goal_refused(self.refusals.stamp(), goal.episode, reason))
            return
        self.settling = False
        self.episode = goal.episode
        rng = seed_streams(goal.seed).sim
        self.state = self.sim.reset(q_start, (goal.goal_m[0], goal.goal_m[1]), rng=rng)
        self.command = None
        self._hold(self.state.q)
        self.reset_pending = True
        log.info("episode %d: arm at its start, button at %s", goal.episode, goal.goal_m)


def main(argv: Sequence[str] | None = None) -> int:
    """Simulation service: the MuJoCo arm on the bus."""
    return run_service(
        "sim",
        "Simulation service: the MuJoCo arm on the bus (real time or lockstep).",
        "DAMMRL_SIM_*, DAMMRL_TASK_*, DAMMRL_ROBOT_*",
        lambda bus, _: SimNode(SimSettings(), TaskSettings(), RobotSettings(), bus),
        argv,
    )
