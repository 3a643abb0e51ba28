"""The robot node: the real arm on the bus, with the sim's contract.

Each loop period it takes what arrived, reads the arm (one sync read), decides the joint
law in force, writes it to the servos (one sync write) and publishes the RobotState,
with the reference actually applied. What is in force, first match wins:

1. a **stop** (emergency stop from the bus, or a fault of the arm: an error bit, a joint
   beyond its limit or its speed): hold where the arm was with the stop gains and gravity
   compensation (or torque off, by ``DAMMRL_ARM_STOP_ACTION``); commands are rejected
   until an emergency stop is released; a fault holds until the service restarts;
2. **homing**: a new episode (TaskGoal) moves the arm slowly to its start posture (a real
   arm cannot be reset); the episode begins, at robot time 0, once it rests there;
3. the controller's **command**, through the arm-side safety function
   (``guard_command``: limits, a cap on |q_ref - q|, rate and freshness);
4. a **hold** where the arm was when commands went stale.

Gains ramp up after every torque-on (soft start). A failed bus cycle leaves the servos on
their last goal; ``max_bus_errors`` in a row is a fault: the servos' watchdog stops them,
the node reports it and reconnects when the bus answers again (an unplugged cable).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from dammrl.core.dynamics import ArmModel
from dammrl.core.robot import RobotDescription, RobotSettings
from dammrl.core.safety import ArmCaps, goal_violation, guard_command, limit_violation
from dammrl.core.state import JointCommand as CoreCommand
from dammrl.core.state import RobotState as CoreState
from dammrl.core.task import TaskSettings, scene_layout
from schemas import EmergencyStop, JointCommand, RobotState, TaskGoal
from services.common import convert
from services.common.arm import CommandFreshness, StopLatch
from services.common.bus import Bus
from services.common.entry import run_service
from services.common.runtime import Pacer
from services.robot.calibration import Calibration, load_calibration
from services.robot.config import ArmSettings
from services.robot.driver import (
    Driver,
    DriverError,
    JointState,
    ServoCommand,
    describe_errors,
    make_driver,
)
from services.robot.recovery import ServoRecovery

log = logging.getLogger("dammrl.robot")
BUTTON_PRESS_TRAVEL_M = 0.003  # as the sim's button


def arm_limits(robot: RobotDescription, calibration: Calibration, settings: ArmSettings
               ) -> RobotDescription:  # fmt: skip
    """The limits this arm runs under with a person attached: the calibration's joint
    limits (inside the URDF's) and fractions of the URDF's speed and effort limits."""
    q_min, q_max = calibration.limits(robot)
    return replace(
        robot,
        q_min=q_min,
        q_max=q_max,
        dq_max=robot.dq_max * settings.speed_fraction,
        tau_max=robot.tau_max * settings.torque_fraction,
    )


@dataclass(frozen=True)
class Homing:
    """A minimum-jerk joint move to an episode's start posture."""

    goal: TaskGoal
    q_from: np.ndarray
    q_to: np.ndarray
    t0_s: float
    duration_s: float

    @classmethod
    def plan(cls, goal: TaskGoal, q: np.ndarray, speed_rad_s: float, now_s: float) -> Homing:
        q_to = np.array(goal.q_start_rad)
        distance = float(np.max(np.abs(q_to - q)))
        return cls(goal, q.copy(), q_to, now_s, max(0.2, 1.875 * distance / speed_rad_s))

    def reference(self, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) of the move at wall time ``now_s``."""
        s = min(max((now_s - self.t0_s) / self.duration_s, 0.0), 1.0)
        shape = 10 * s**3 - 15 * s**4 + 6 * s**5
        rate = (30 * s**2 - 60 * s**3 + 30 * s**4) / self.duration_s
        delta = self.q_to - self.q_from
        return self.q_from + shape * delta, rate * delta


class RobotNode:
    def __init__(
        self,
        settings: ArmSettings,
        task: TaskSettings,
        robot: RobotSettings,
        bus: Bus,
        driver: Driver | None = None,
    ) -> None:
        self.settings = settings
        self.bus = bus
        self.description = robot.load()
        self.calibration = (
            Calibration()
            if settings.calibration_file is None
            else load_calibration(settings.calibration_file)
        )
        self.limits = arm_limits(self.description, self.calibration, settings)
        self.layout = scene_layout(task)
        self.arm = ArmModel(self.description)
        self.driver = driver or make_driver(
            settings.driver, port=settings.port, calibration=self.calibration,
            baud=settings.baud, watchdog_s=settings.watchdog_s,
        )  # fmt: skip
        self.caps = ArmCaps(
            settings.limit_tolerance_rad, settings.max_kp_nm_per_rad, settings.max_kd_nms_per_rad,
            settings.max_relative_target_rad, 1.0,  # the speed fraction is in self.limits
        )  # fmt: skip
        self.pacer = Pacer(1.0 / settings.loop_rate_hz)
        self.freshness = CommandFreshness(round(settings.command_max_age_s * settings.loop_rate_hz))
        self.stop_latch = StopLatch()
        self.fault: str | None = None  # the arm's own stop (error bits, limits), latched
        self.recovery = ServoRecovery(settings.max_reboots)
        self.reported_stopped = False
        self.bus_fault: str | None = None  # the bus is gone: reconnecting
        self.connected = False
        self.limp = False  # a stop turned the torque off: the state is read, nothing written
        self.torque_on_s = 0.0
        self.next_connect_s = 0.0
        self.bus_errors = 0
        self.episode = 0
        self.episode_t0_s = time.monotonic()
        self.homing: Homing | None = None
        self.unreachable_episode = -1  # its start posture was not reached: refused
        self.homing_failure: str | None = None
        self.command: CoreCommand | None = None  # the controller's, after the caps
        self.command_wall_s = 0.0
        self.command_stamp_ns = 0  # header stamp of the command in force
        self.latency_pending = False  # the command in force is not yet written
        self.in_force_answers_ns: int | None = None
        self.held: CoreCommand | None = None  # a hold or a stop's law, fixed when it began
        self.last_q_ref: np.ndarray | None = None
        self.joint: JointState | None = None
        self.last_written: ServoCommand | None = None  # the law last sent to the servos
        self.last_write_s = float("inf")  # when (monotonic); inf: not since connecting
        self.clamped = 0
        self.periods_s: deque[float] = deque(maxlen=10_000)
        self.latencies_s: deque[float] = deque(maxlen=10_000)  # command stamp -> written
        self.last_cycle_s: float | None = None
        self.state_publisher = bus.publisher(RobotState)
        bus.subscribe(JointCommand, TaskGoal, EmergencyStop)
        bus.expect(JointCommand, "controller")
        bus.expect(TaskGoal, "controller")
        bus.expect(EmergencyStop, "tool")  # `dammrl stop` (the operator)

    # ---- the loop ----------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        log.info("driving the arm on %s at %.0f Hz", self.settings.port, self.settings.loop_rate_hz)
        self.pacer.restart()
        try:
            while not stop.is_set():
                self.pacer.wait()
                self.cycle()
        finally:
            if self.connected:
                self.driver.disconnect()  # the servos hold where they are

    def cycle(self) -> None:
        """One period: messages, read, decide, write, publish."""
        now = time.monotonic()
        if self.last_cycle_s is not None:
            self.periods_s.append(now - self.last_cycle_s)
        self.last_cycle_s = now
        self._take_messages()
        if not self.connected and self.bus_fault is not None:
            self._hold_blind()
        if not self.connected:
            self._try_connect(now)
        if self.connected:
            self._drive(now)
        self._report_health()

    def _drive(self, now: float) -> None:
        try:
            joint = self.driver.read_state()
            self._check(joint)
            if now - self.last_write_s > self.settings.watchdog_s:
                self._after_stall(joint, now)
            law = self._law(joint, now)
            if law is not None:
                self.driver.write_command(law)
                self.last_written, self.last_write_s = law, now
                if self.latency_pending:  # a new command's first write
                    self.latencies_s.append(time.time() - self.command_stamp_ns * 1e-9)
                    self.latency_pending = False
        except DriverError as exc:
            self._bus_error(exc)
            return
        self.bus_errors = 0
        self.joint = joint
        self._publish_state(joint, now)

    # ---- the bus: messages in ----------------------------------------------------------
    def _take_messages(self) -> None:
        for message in self.bus.receive_all(0):
            if isinstance(message, EmergencyStop):
                self._take_stop(message)
            elif isinstance(message, TaskGoal):
                self._take_goal(message)
            elif isinstance(message, JointCommand):
                self._take_command(message)

    def _take_stop(self, message: EmergencyStop) -> None:
        if not self.stop_latch.take(message):
            return
        if self.stop_latch.engaged:
            log.warning("%s: stopping (%s)", self.stop_latch.reason, self.settings.stop_action)
            self._stop()
        else:
            log.warning("emergency stop released: holding until commands resume")
            if self.limp and self.fault is None:
                self._reconnect_now()  # torque back on, with the soft start

    def _take_goal(self, goal: TaskGoal) -> None:
        if goal.episode == self.episode or (
            self.homing and self.homing.goal.episode == goal.episode
        ):
            return  # a repeated announcement
        if goal.episode == self.unreachable_episode:
            self.bus.reject(self.bus.key(TaskGoal), self.homing_failure or "unreachable")
            return
        reason = self.stop_latch.reason or self.fault or self.bus_fault
        joint = self.joint
        if reason is None and joint is None:
            reason = "the arm is not connected"
        if reason is None and joint is not None:
            reason = goal_violation(
                np.array(goal.q_start_rad), goal.goal_m, self.limits, self.layout,
                self.settings.limit_tolerance_rad,
            )  # fmt: skip
        if reason is not None or joint is None:
            self.bus.reject(self.bus.key(TaskGoal), reason or "no state")
            return
        self.homing = Homing.plan(goal, joint.q_rad, self.settings.homing_speed_rad_s,
                                  time.monotonic())  # fmt: skip
        self.command = self.held = None
        log.info("episode %d: moving to the start posture (%.1f s)", goal.episode,
                 self.homing.duration_s)  # fmt: skip

    def _take_command(self, message: JointCommand) -> None:
        key = self.bus.key(JointCommand)
        if message.episode != self.episode or self.homing is not None:
            return  # for an episode this arm has not begun (or has left)
        blocked = self.stop_latch.reason or self.fault or self.bus_fault
        if blocked is not None or self.joint is None:
            self.bus.reject(key, blocked or "the arm is not connected")
            return
        reason = self.freshness.why_stale(message.state_stamp_ns)
        now_s = time.monotonic()
        dt = self.freshness.allowance_s(message.state_stamp_ns, 2 * self.pacer.period_s)
        guarded = guard_command(
            convert.joint_command(message), self.joint.q_rad, self.last_q_ref, dt,
            self.limits, self.caps,
        )  # fmt: skip
        reason = reason or (None if guarded.clamped else guarded.reason)
        if reason is not None or guarded.command is None:
            self.bus.reject(key, reason or "rejected")
            return
        if guarded.clamped:
            self.clamped += 1
            if self.clamped <= 5 or self.clamped % 100 == 0:
                log.warning("command #%d clamped: %s", self.clamped, guarded.reason)
        if self.held is not None:
            log.info("commands resumed: leaving the hold")
        self.command, self.held = guarded.command, None
        self.freshness.applied(message.state_stamp_ns)
        self.in_force_answers_ns = message.state_stamp_ns
        self.command_wall_s = now_s
        self.command_stamp_ns = message.header.stamp_ns
        self.latency_pending = True

    # ---- deciding the law --------------------------------------------------------------
    def _check(self, joint: JointState) -> None:
        """Latch a fault on an error bit, a joint beyond its limits or its speed; reboot a
        servo that cut its torque, and hold its joint where it is once it is back."""
        for j in self.recovery.rebooting - joint.rebooting:  # read this cycle: it is back
            self._servo_back(j, joint)
        if joint.hardware_errors:
            reason = "; ".join(f"servo {i}: {describe_errors(bits)}"
                               for i, bits in joint.hardware_errors.items())  # fmt: skip
            self._latch(reason, joint.q_rad)
            for servo_id, bits in joint.hardware_errors.items():
                self._recover(servo_id, bits)
        elif self.fault is None:
            beyond = limit_violation(
                self.limits, joint.q_rad, joint.dq_rad_s, self.settings.limit_tolerance_rad,
                self.settings.overspeed_stop_fraction / self.settings.speed_fraction,
            )  # fmt: skip
            if beyond is not None:
                self._latch(beyond, joint.q_rad)

    def _latch(self, reason: str, q: np.ndarray) -> None:
        if self.fault is None:
            self.fault = reason
            log.error("arm fault: %s: stopping", reason)
            self._stop(q)

    def _recover(self, servo_id: int, bits: int) -> None:
        """Reboot a servo whose overload cut its torque (the others hold meanwhile)."""
        if servo_id not in self.calibration.ids or self.settings.stop_action != "hold":
            return
        joint = self.calibration.ids.index(servo_id)
        if self.recovery.fault(joint, servo_id, bits):
            log.error("%s", self.recovery.notes[joint])
            self.driver.reboot(joint)
        elif joint in self.recovery.off:
            log.error("%s", self.recovery.notes[joint])

    def _servo_back(self, j: int, joint: JointState) -> None:
        """A rebooted servo holds where its joint is now: the stop's law there too."""
        self.recovery.back(j, self.calibration.ids[j], float(joint.q_rad[j]))
        log.warning("%s", self.recovery.notes[j])
        if self.held is not None:
            q_ref = self.held.q_ref.copy()
            q_ref[j] = joint.q_rad[j]
            self.held = self._hold_law(q_ref, self.held.kp, self.held.kd)

    def _stop(self, q: np.ndarray | None = None) -> None:
        """Hold where the arm is now, with the stop gains; or torque off."""
        self.homing = None
        self.command = None
        if self.settings.stop_action == "torque_off":
            if self.connected:
                self.driver.torque_off()
            self.limp = True  # nothing is written until a release reconnects
            return
        where = q if q is not None else (None if self.joint is None else self.joint.q_rad)
        if where is not None:
            self.held = self._hold_law(where, np.array(self.settings.stop_kp_nm_per_rad),
                                       np.array(self.settings.stop_kd_nms_per_rad))  # fmt: skip

    def _law(self, joint: JointState, now: float) -> ServoCommand | None:
        """The joint law to write this period (None: the torque is off)."""
        if (self.stop_latch.engaged or self.fault is not None) and self.held is None:
            self._stop(joint.q_rad)  # stopped while the bus was away: hold where it is now
        if self.limp:
            return None
        if self.homing is not None:
            law = self._homing_law(joint, now)
        elif self.held is not None:
            law = self.held
        elif (
            self.command is not None and now - self.command_wall_s <= self.settings.command_stale_s
        ):
            law = self.command
        else:
            law = self._begin_hold(joint.q_rad)
        self.last_q_ref = law.q_ref
        ramp = self._soft_start(now)
        return ServoCommand(
            law.q_ref, law.dq_ref, law.tau_ff, law.kp * ramp, law.kd * ramp, self.limits.tau_max
        )

    def _after_stall(self, joint: JointState, now: float) -> None:
        """This process was silent longer than the servos' watchdog (a stall, a swap): the
        servos stopped by themselves and refuse goals until re-armed. Re-arm them and hold
        where the arm is (a homing move starts again from there): nothing resumes a
        motion planned before the stall."""
        stopped = self.driver.rearm_watchdog()
        if not stopped:
            return
        log.warning("silent %.0f ms: the watchdog had stopped servos %s; holding where the "
                    "arm is", (now - self.last_write_s) * 1000, stopped)  # fmt: skip
        if self.homing is not None:
            goal = self.homing.goal
            self.homing = Homing.plan(goal, joint.q_rad, self.settings.homing_speed_rad_s, now)
        elif self.held is None:
            self._begin_hold(joint.q_rad)

    def _begin_hold(self, q: np.ndarray) -> CoreCommand:
        """Commands went stale (or never came): hold here with the last command's gains."""
        if self.command is not None:
            who = "alive but silent" if "controller" in self.bus.alive_peers() else "gone"
            log.warning("no valid command from the controller (%s) for %.2f s: holding",
                        who, self.settings.command_stale_s)  # fmt: skip
        last = self.command
        kp = last.kp if last is not None else np.array(self.settings.hold_kp_nm_per_rad)
        kd = last.kd if last is not None else np.array(self.settings.hold_kd_nms_per_rad)
        self.command = None
        self.in_force_answers_ns = None
        self.held = self._hold_law(q, kp, kd)
        return self.held

    def _hold_law(self, q: np.ndarray, kp: np.ndarray, kd: np.ndarray) -> CoreCommand:
        self.freshness.held(time.monotonic() - self.episode_t0_s)
        zeros = np.zeros(6)
        return CoreCommand(q.copy(), zeros, self.arm.inverse_dynamics(q, zeros, zeros), kp, kd)

    def _homing_law(self, joint: JointState, now: float) -> CoreCommand:
        homing = self.homing
        assert homing is not None
        q_ref, dq_ref = homing.reference(now)
        resting = float(np.max(np.abs(joint.dq_rad_s))) < self.settings.rest_speed_rad_s
        there = (
            float(np.max(np.abs(joint.q_rad - homing.q_to))) < self.settings.homing_tolerance_rad
        )
        late = now - homing.t0_s - homing.duration_s
        if late >= 0 and resting and there:
            self._begin_episode(homing.goal, now)
        elif late > self.settings.homing_timeout_s:
            return self._give_up_homing(homing, joint)
        gravity = self.arm.inverse_dynamics(q_ref, np.zeros(6), np.zeros(6))
        kp, kd = (
            np.array(self.settings.hold_kp_nm_per_rad),
            np.array(self.settings.hold_kd_nms_per_rad),
        )
        return CoreCommand(q_ref, dq_ref, gravity, kp, kd)

    def _give_up_homing(self, homing: Homing, joint: JointState) -> CoreCommand:
        """The start posture was not reached: refuse the episode, hold where the arm is."""
        miss = float(np.max(np.abs(joint.q_rad - homing.q_to)))
        self.homing_failure = (
            f"episode {homing.goal.episode}: the start posture not reached ({miss:.3f} rad "
            f"away {self.settings.homing_timeout_s:.1f} s after the move): holding"
        )
        log.error("%s", self.homing_failure)
        self.unreachable_episode = homing.goal.episode
        self.bus.reject(self.bus.key(TaskGoal), self.homing_failure)
        self.homing = None
        return self._begin_hold(joint.q_rad)

    def _begin_episode(self, goal: TaskGoal, now: float) -> None:
        self.homing = None
        self.episode = goal.episode
        self.episode_t0_s = now
        self.held = self._hold_law(np.array(goal.q_start_rad),
                                   np.array(self.settings.hold_kp_nm_per_rad),
                                   np.array(self.settings.hold_kd_nms_per_rad))  # fmt: skip
        log.info("episode %d: the arm rests at its start", goal.episode)

    def _soft_start(self, now: float) -> float:
        """The gains' share after torque-on: from ``soft_start_fraction`` to 1, linearly."""
        duration = self.settings.soft_start_s
        if duration <= 0:
            return 1.0
        share = min((now - self.torque_on_s) / duration, 1.0)
        low = self.settings.soft_start_fraction
        return low + (1.0 - low) * max(share, 0.0)

    # ---- connection and faults ---------------------------------------------------------
    def _try_connect(self, now: float) -> None:
        if now < self.next_connect_s:
            return
        self.next_connect_s = now + self.settings.reconnect_s
        try:
            holding = self.driver.connect()
        except DriverError as exc:
            if self.bus_fault != str(exc):
                log.error("%s: retrying every %.1f s", exc, self.settings.reconnect_s)
            self.bus_fault = str(exc)
            return
        # servos that held with the torque on need no soft start (it would drop the arm)
        self.connected = True
        self.torque_on_s = time.monotonic() - (self.settings.soft_start_s if holding else 0.0)
        self.last_write_s = float("inf")  # connect armed the watchdog: no stall to look for
        if self.bus_fault is not None:
            log.warning("the servo bus answers again: holding where the arm is")
        self.bus_fault = None
        self.bus_errors = 0
        self.command, self.homing, self.held = None, None, None  # a stop is taken up by _law

    def _reconnect_now(self) -> None:
        if self.connected:
            self.driver.disconnect()
        self.connected = self.limp = False
        self.next_connect_s = 0.0

    def _bus_error(self, exc: DriverError) -> None:
        """A failed cycle: the servos keep their last goal; too many in a row: a fault.
        Then the last law is still sent every period (a sync write needs no answer): the
        servos that still hear it hold with gravity compensation; the others' watchdog
        stops them where they are."""
        self.bus_errors += 1
        if self.bus_errors < self.settings.max_bus_errors:
            log.warning("bus cycle failed (%d in a row): %s", self.bus_errors, exc)
            return
        self.bus_fault = f"servo bus lost: {exc}"
        log.error("%s: holding blind, reconnecting", self.bus_fault)
        self.connected = False
        self.joint = None
        self.command, self.homing, self.held = None, None, None
        self.next_connect_s = time.monotonic() + self.settings.reconnect_s

    def _hold_blind(self) -> None:
        if self.last_written is not None:
            with contextlib.suppress(DriverError):
                self.driver.write_command(self.last_written)

    # ---- the bus: out ------------------------------------------------------------------
    def _publish_state(self, joint: JointState, now: float) -> None:
        ee, jacobian = self.arm.ee_position_and_jacobian(joint.q_rad)
        state = CoreState(
            t_s=now - self.episode_t0_s,
            q=joint.q_rad,
            dq=joint.dq_rad_s,
            tau=joint.tau_nm,
            ee_pos=ee,
            ee_vel=jacobian @ joint.dq_rad_s,
            button_pressed=joint.button_travel_m >= BUTTON_PRESS_TRAVEL_M,
            button_travel_m=joint.button_travel_m,
        )
        holding = self.command is None
        message = self.state_publisher.publish(
            **convert.state_fields(
                state,
                self.episode,
                holding,
                self.last_q_ref,
                None if holding else self.in_force_answers_ns,
            )
        )
        self.freshness.published(message.header.stamp_ns, state.t_s)

    def _report_health(self) -> None:
        """Health every period of the bus's, and at once when the arm stops or resumes."""
        reason = self.stop_latch.reason or self.fault
        if reason is not None:
            state, detail = "stopped", "; ".join(filter(None, (reason, self.recovery.detail())))
        elif self.bus_fault is not None:
            state, detail = "degraded", self.bus_fault
        else:
            state = "holding" if self.command is None else "ok"
            detail = "; ".join(filter(None, (self.homing_failure, self.timing())))
        changed = (state == "stopped") != self.reported_stopped
        self.reported_stopped = state == "stopped"
        self.bus.report_health(state, detail, force=changed)

    def timing(self) -> str:
        """Loop period p50/p99 and command-to-applied latency p50/p99 (Health detail)."""
        parts = []
        if len(self.periods_s) > 10:
            p50, p99 = np.percentile(self.periods_s, [50, 99]) * 1000
            parts.append(f"loop period p50 {p50:.2f} ms, p99 {p99:.2f} ms")
        if len(self.latencies_s) > 10:
            p50, p99 = np.percentile(self.latencies_s, [50, 99]) * 1000
            parts.append(f"command to servo p50 {p50:.2f} ms, p99 {p99:.2f} ms")
        parts.append(f"{self.clamped} commands clamped")
        return ", ".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    """Robot service: the real arm (a Dynamixel chain) on the bus."""
    return run_service(
        "robot",
        "Robot service: the real arm on the bus, the sim's contract (stage S3).",
        "DAMMRL_ARM_*, DAMMRL_TASK_*, DAMMRL_ROBOT_*",
        lambda bus, _: RobotNode(ArmSettings(), TaskSettings(), RobotSettings(), bus),
        argv,
    )
