"""The robot node: the real arm on the bus, with the sim's contract.

Each loop period it takes what arrived, reads the arm (one read of every drive), decides
the joint law in force (``law.ArmLaw``: stop, homing, command or hold), writes it (one
write) and publishes the RobotState, with the reference actually applied. The drives'
link (``link.DriveLink``) connects, holds blind through a lost bus and reconnects; the
driver is a plug-in (``DAMMRL_ARM_DRIVER``: the built-in ``dynamixel`` or an installed
package's), made from its own settings.
"""

from __future__ import annotations

import inspect
import logging
import threading
import time
from collections import deque
from collections.abc import Sequence

import numpy as np

from dammrl_core.arm.driver import DriveCommand, Driver, DriverError, JointState, driver_plugin
from dammrl_core.arm.settings import ArmSettings, arm_limits
from dammrl_core.dynamics import ArmModel
from dammrl_core.errors import ConfigurationError
from dammrl_core.robot import RobotSettings
from dammrl_core.state import RobotState as CoreState
from dammrl_core.task import TaskSettings, scene_layout
from schemas import EmergencyStop, GoalRefused, JointCommand, RobotState, TaskGoal
from schemas.messages import HealthState
from services.common import convert
from services.common.bus import Bus
from services.common.entry import run_service
from services.common.runtime import Pacer
from services.common.security import OPERATOR
from services.robot.law import ArmLaw, Start
from services.robot.link import DriveLink

log = logging.getLogger("dammrl.robot")
BUTTON_PRESS_TRAVEL_M = 0.003  # as the sim's button
UNFOLLOWED_RAD = 0.1
UNFOLLOWED_S = 1.0
"""A reference the arm has not followed for this long (this far from it, at rest): the
drives are asked whether they stopped themselves (a sync write they refuse says nothing,
and a packet held back can let their watchdog run out with no failed cycle here). Their
answer costs one read per drive; the controller's own never lag this far (0.054 rad)."""
START_RETRIES = 2
"""How often an episode whose start was missed by drives stopped on their own clock is
tried again; then it is refused all the same (drives that stop on every try would
otherwise hold the session on that episode for good)."""


def make_driver(settings: ArmSettings) -> Driver:
    """The driver ``settings.driver`` names, made from its own settings; refused (one
    line, at start) if it cannot hold the arm from its torque-on."""
    plugin = driver_plugin(settings.driver)
    driver = plugin.create(plugin.settings())
    if "hold" not in inspect.signature(driver.connect).parameters:
        raise ConfigurationError(
            f"the arm driver {settings.driver!r} has connect() without 'hold': it would turn "
            "the torque on with no law in force; update it to dammrl_core.arm.driver.Driver"
        )
    return driver


class RobotNode:
    def __init__(self, settings: ArmSettings, task: TaskSettings, robot: RobotSettings,
                 bus: Bus, driver: Driver | None = None) -> None:  # fmt: skip
        self.settings = settings
        self.bus = bus
        self.description = robot.load()
        self.link = DriveLink(driver or make_driver(settings), settings)
        limits = arm_limits(self.description, self.link.driver.joint_limits(self.description),
                            settings)  # fmt: skip
        self.arm = ArmModel(self.description)
        self.pacer = Pacer(1.0 / settings.loop_rate_hz)
        self.law = ArmLaw(settings, limits, scene_layout(task), self.arm, self.pacer.period_s,
                          time.monotonic())  # fmt: skip
        self.joint: JointState | None = None
        self.reported_stopped = False
        self.command_stamp_ns = 0  # header stamp of the command in force
        self.latency_pending = False  # the command in force is not yet written
        self.start_retries: dict[int, int] = {}  # episode -> tries after stopped drives
        self.unfollowed_since: float | None = None  # the arm at rest far from its reference
        self.periods_s: deque[float] = deque(maxlen=10_000)
        self.latencies_s: deque[float] = deque(maxlen=10_000)  # command stamp -> written
        self.last_cycle_s: float | None = None
        self.state_publisher = bus.publisher(RobotState)
        self.refusals = bus.publisher(GoalRefused)
        bus.subscribe(JointCommand, TaskGoal, EmergencyStop)
        bus.expect(JointCommand, "controller")
        bus.expect(TaskGoal, "controller")
        bus.expect(EmergencyStop, OPERATOR)  # `dammrl stop` (the operator)

    @property
    def driver(self) -> Driver:
        return self.link.driver

    @property
    def connected(self) -> bool:
        return self.link.connected

    # ---- the loop ----------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        log.info("driving the arm (%s) at %.0f Hz", self.settings.driver,
                 self.settings.loop_rate_hz)  # fmt: skip
        self.pacer.restart()
        try:
            while not stop.is_set():
                self.pacer.wait()
                self.cycle()
        finally:
            self.link.close()

    def cycle(self) -> None:
        """One period: messages, read, decide, write, publish."""
        now = time.monotonic()
        if self.last_cycle_s is not None:
            self.periods_s.append(now - self.last_cycle_s)
        self.last_cycle_s = now
        self._take_messages(now)
        if not self.link.connected and self.link.fault is not None:
            self.link.hold_blind()
        if not self.link.connected:
            self.law.forget_motion()  # nothing survives a lost bus; a stop is kept by the law
            self.link.try_connect(now, lambda joint: self._torque_on_law(joint, now))
        if self.link.connected:
            self._drive(now)
        self._report_health()

    def _drive(self, now: float) -> None:
        try:
            joint = self.link.read()
            if self.law.check(joint, self.driver.restart):
                self._stop(joint.q_rad, now)
            if self.link.stalled(now):
                self._after_stall(joint, now)
            if not self.link.limp:
                ramp = self.link.soft_start(now)
                self.link.write(self.law.law(joint, now, ramp, self._controller_silence), now)
                self._note_written()
                self._doubt_if_unfollowed(joint, now)
            self._refuse_episodes(joint, now)  # may ask the drives
        except DriverError as exc:
            if self.link.failed(exc):
                self.joint = None
                self.law.forget_motion()
            return
        self.link.cycle_done()
        self.joint = joint
        self._publish_state(joint, now)

    def _torque_on_law(self, joint: JointState, now: float) -> DriveCommand:
        """What the drives hold with from their torque-on: the law's hold (or stop) where
        the arm is, at the soft start's first stiffness, the damping whole."""
        return self.law.law(joint, now, self.link.soft_start(now), self._controller_silence)

    def _stop(self, q: np.ndarray | None, now: float) -> None:
        """Hold where the arm is with the stop gains; or torque off."""
        if self.settings.stop_action == "torque_off":
            self.law.forget_motion()
            self.link.torque_off()
        elif q is not None:
            self.law.stop_here(q, now)

    def _after_stall(self, joint: JointState, now: float) -> bool:
        """The drives may have seen a longer silence than they allow (this process stalled
        or swapped, or a cycle failed): those that stopped by themselves refuse goals until
        re-armed. Whether any had."""
        stopped = self.driver.rearm()
        self.link.doubt_drives = False
        if stopped:
            log.warning("the drives %s had stopped themselves (%.0f ms since this host's last "
                        "write, by its clock); holding where the arm is", stopped,
                        (now - self.link.last_write_s) * 1000)  # fmt: skip
            self.law.after_stall(joint, now)
        return bool(stopped)

    def _doubt_if_unfollowed(self, joint: JointState, now: float) -> None:
        """Ask the drives at the next cycle whether they stopped themselves, when the arm
        has rested ``UNFOLLOWED_RAD`` from its reference for ``UNFOLLOWED_S``."""
        q_ref = self.law.last_q_ref
        resting = float(np.max(np.abs(joint.dq_rad_s))) < self.settings.rest_speed_rad_s
        if q_ref is None or not resting or np.max(np.abs(q_ref - joint.q_rad)) < UNFOLLOWED_RAD:
            self.unfollowed_since = None
        elif self.unfollowed_since is None:
            self.unfollowed_since = now
        elif now - self.unfollowed_since >= UNFOLLOWED_S:
            self.link.doubt_drives, self.unfollowed_since = True, None

    def _refuse_episodes(self, joint: JointState, now: float) -> None:
        """Tell the controller of each episode this arm cannot begin (it ends it as a hold
        and goes on). A start posture not reached may be the drives' doing, stopped by
        their own clock with nothing to tell this host: they are asked first, and if they
        had stopped, re-armed and the episode, announced again, is tried again."""
        refused, self.law.refused = dict(self.law.refused), []  # once per episode
        for episode, reason in refused.items():
            tries = self.start_retries.get(episode, 0)
            retry = episode == self.law.unreachable_episode and tries < START_RETRIES
            if retry and self._after_stall(joint, now):
                self.start_retries[episode] = tries + 1
                log.warning("episode %d: tried again when announced (the drives had stopped)",
                            episode)  # fmt: skip
                continue
            self.bus.reject(self.bus.key(TaskGoal), reason)
            self.refusals.send(convert.goal_refused(self.refusals.stamp(), episode, reason))

    def _note_written(self) -> None:
        if self.latency_pending:  # a new command's first write
            self.latencies_s.append(time.time() - self.command_stamp_ns * 1e-9)
            self.latency_pending = False

    def _controller_silence(self) -> str:
        return "alive but silent" if "controller" in self.bus.alive_peers() else "gone"

    # ---- the bus: messages in ----------------------------------------------------------
    def _take_messages(self, now: float) -> None:
        for message in self.bus.receive_all(0):
            if isinstance(message, EmergencyStop):
                self._take_stop(message, now)
            elif isinstance(message, TaskGoal):
                self._take_goal(message, now)
            elif isinstance(message, JointCommand):
                self._take_command(message, now)

    def _take_stop(self, message: EmergencyStop, now: float) -> None:
        latch = self.law.stop_latch
        if not latch.take(message.engaged, message.header.source, message.reason):
            return
        if latch.engaged:
            log.warning("%s: stopping (%s)", latch.reason, self.settings.stop_action)
            self._stop(None if self.joint is None else self.joint.q_rad, now)
        else:
            log.warning("emergency stop released: holding until commands resume")
            if self.link.limp and self.law.fault is None:
                self.link.reconnect_now()  # torque back on, with the soft start
            elif self.joint is not None and self.law.fault is None:
                self.law.release_here(self.joint.q_rad, now)

    def _take_goal(self, goal: TaskGoal, now: float) -> None:
        # the tries of the episode announced only (a restarted controller counts from 1)
        self.start_retries = {e: n for e, n in self.start_retries.items() if e == goal.episode}
        joint = self.joint
        reason = self.link.fault or (None if joint is not None else "the arm is not connected")
        if reason is None and joint is not None:
            start = Start(goal.episode, np.array(goal.q_start_rad))
            reason = self.law.take_goal(start, goal.goal_m, joint, now)
        if reason is not None:
            self.bus.reject(self.bus.key(TaskGoal), reason)

    def _take_command(self, message: JointCommand, now: float) -> None:
        if message.episode != self.law.episode or self.law.homing is not None:
            return  # for an episode this arm has not begun (or has left)
        joint = self.joint
        if joint is None:
            reason: str | None = self.link.fault or "the arm is not connected"
        else:
            command = convert.joint_command(message)
            reason = self.link.fault or self.law.take_command(
                command, message.state_stamp_ns, joint, now
            )
        if reason is not None:
            self.bus.reject(self.bus.key(JointCommand), reason)
            return
        self.command_stamp_ns = message.header.stamp_ns
        self.latency_pending = True

    # ---- the bus: out ------------------------------------------------------------------
    def _publish_state(self, joint: JointState, now: float) -> None:
        ee, jacobian = self.arm.ee_position_and_jacobian(joint.q_rad)
        state = CoreState(
            t_s=self.law.t_s(now),
            q=joint.q_rad,
            dq=joint.dq_rad_s,
            tau=joint.tau_nm,
            ee_pos=ee,
            ee_vel=jacobian @ joint.dq_rad_s,
            button_pressed=joint.button_travel_m >= BUTTON_PRESS_TRAVEL_M,
            button_travel_m=joint.button_travel_m,
        )
        holding = self.law.command is None
        message = self.state_publisher.send(
            convert.state_message(
                self.state_publisher.stamp(),
                state,
                self.law.episode,
                holding,
                self.law.last_q_ref,
                None if holding else self.law.in_force_answers_ns,
            )
        )
        self.law.freshness.published(message.header.stamp_ns, state.t_s)

    def _report_health(self) -> None:
        """Health every period of the bus's, and at once when the arm stops or resumes."""
        reason = self.law.stopped
        state: HealthState
        if reason is not None:
            detail = "; ".join(filter(None, (reason, self.law.recovery.detail())))
            state = "stopped"
        elif self.link.fault is not None:
            state, detail = "degraded", self.link.fault
        else:
            state = "holding" if self.law.command is None else "ok"
            detail = "; ".join(filter(None, (self.law.homing_failure, self.timing())))
        changed = (state == "stopped") != self.reported_stopped
        self.reported_stopped = state == "stopped"
        self.bus.report_health(state, detail, force=changed)

    def timing(self) -> str:
        """Loop period p50/p99, command-to-applied latency p50/p99, clamped commands and
        failed bus cycles (a timeout, a bad answer) since the start (Health detail)."""
        parts = []
        if len(self.periods_s) > 10:
            p50, p99 = np.percentile(self.periods_s, [50, 99]) * 1000
            parts.append(f"loop period p50 {p50:.2f} ms, p99 {p99:.2f} ms")
        if len(self.latencies_s) > 10:
            p50, p99 = np.percentile(self.latencies_s, [50, 99]) * 1000
            parts.append(f"command to servo p50 {p50:.2f} ms, p99 {p99:.2f} ms")
        parts.append(f"{self.law.freshness.clamped} commands clamped")
        parts.append(f"{self.link.bus_errors} bus errors")
        return ", ".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    """Robot service: the real arm on the bus."""
    return run_service(
        "robot",
        "Robot service: the real arm on the bus, the sim's contract (stage S3).",
        "DAMMRL_ARM_*, the driver's own (e.g. DAMMRL_DYNAMIXEL_*), DAMMRL_TASK_*, DAMMRL_ROBOT_*",
        lambda bus, _: RobotNode(ArmSettings(), TaskSettings(), RobotSettings(), bus),
        argv,
    )
