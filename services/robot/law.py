"""Which joint law the real arm follows, first match wins:

1. a **stop** (an emergency stop from the bus, or the arm's own fault: a drive's fault, a
   joint beyond its limit or its speed): hold where the arm was with the stop gains and
   gravity compensation (or torque off, by ``DAMMRL_ARM_STOP_ACTION``); commands are
   refused until an emergency stop is released; a fault holds until the service restarts,
   a drive whose overload cut its torque is restarted and holds again where it is;
2. **homing**: a new episode (TaskGoal) moves the arm slowly to its start posture (a real
   arm cannot be reset) on the move's own clock, which a late cycle cannot jump ahead
   (dammrl_core.arm.start); the episode begins, at robot time 0, once it rests there;
3. the controller's **command**, through the arm-side safety function (``guard_command``:
   limits, a cap on |q_ref - q|, rate and freshness);
4. a **hold** where the arm was when commands went stale.

After the drives stopped themselves (this process stalled longer than their watchdog),
every law starts again from the measured posture: a hold or a stop holds there, homing
plans its move from there.

No bus and no driver here: messages come in as arguments, the law goes out as a value.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dammrl_core.arm.driver import DriveCommand, DriverError, JointState
from dammrl_core.arm.recovery import DriveRecovery
from dammrl_core.arm.settings import ArmSettings
from dammrl_core.arm.start import LATE_CYCLE_S, MotionClock, softened
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotDescription
from dammrl_core.robot.scene import SceneLayout
from dammrl_core.safety import (
    ArmCaps,
    CommandFreshness,
    StopLatch,
    goal_violation,
    guard_command,
    limit_violation,
)
from dammrl_core.state import JointCommand as CoreCommand

log = logging.getLogger("dammrl.robot")


@dataclass(frozen=True)
class Start:
    """A new episode's start: its number and posture."""

    episode: int
    q_rad: np.ndarray


@dataclass
class Homing:
    """A minimum-jerk joint move to an episode's start posture, on its own clock."""

    start: Start
    q_from: np.ndarray
    duration_s: float
    clock: MotionClock
    ended_s: float | None = None  # the wall time its clock reached the move's end

    @classmethod
    def plan(cls, start: Start, q: np.ndarray, speed_rad_s: float, now_s: float,
             max_step_s: float) -> Homing:  # fmt: skip
        """From ``q`` at wall time ``now_s``; the move's clock advances by at most
        ``max_step_s`` a cycle."""
        distance = float(np.max(np.abs(start.q_rad - q)))
        clock = MotionClock(max_step_s)
        clock.advance(now_s)
        return cls(start, q.copy(), max(0.2, 1.875 * distance / speed_rad_s), clock)

    def reference(self, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(q, dq) of the move, its clock advanced to wall time ``now_s``."""
        s = min(self.clock.advance(now_s) / self.duration_s, 1.0)
        if s >= 1.0 and self.ended_s is None:
            self.ended_s = now_s
        shape = 10 * s**3 - 15 * s**4 + 6 * s**5
        rate = (30 * s**2 - 60 * s**3 + 30 * s**4) / self.duration_s
        delta = self.start.q_rad - self.q_from
        return self.q_from + shape * delta, rate * delta

    def since_end(self, now_s: float) -> float:
        """Wall time since the move's end [s] (negative: not at its end yet)."""
        return -1.0 if self.ended_s is None else now_s - self.ended_s


class ArmLaw:
    """The arm's state machine: stop, homing, command, hold."""

    def __init__(self, settings: ArmSettings, limits: RobotDescription, layout: SceneLayout,
                 arm: ArmModel, period_s: float, now_s: float) -> None:  # fmt: skip
        self.settings = settings
        self.limits = limits
        self.layout = layout
        self.arm = arm
        self.period_s = period_s
        self.max_step_s = LATE_CYCLE_S  # what a late cycle advances homing's clock by, at most
        self.caps = ArmCaps(
            settings.limit_tolerance_rad, settings.max_kp_nm_per_rad, settings.max_kd_nms_per_rad,
            settings.max_relative_target_rad, 1.0,  # the speed fraction is in the limits
        )  # fmt: skip
        self.freshness = CommandFreshness(round(settings.command_max_age_s / period_s))
        self.stop_latch = StopLatch()
        self.fault: str | None = None  # the arm's own stop (drive faults, limits), latched
        self.recovery = DriveRecovery(settings.max_restarts)
        self.said: dict[int, str] = {}  # joint -> the last word logged on its drive
        self.episode, self.episode_t0_s = 0, now_s
        self.homing: Homing | None = None
        self.unreachable_episode = -1  # its start posture was not reached: refused
        self.homing_failure: str | None = None
        self.command: CoreCommand | None = None  # the controller's, after the caps
        self.command_wall_s = 0.0
        self.in_force_answers_ns: int | None = None
        self.held: CoreCommand | None = None  # a hold or a stop's law, fixed when it began
        self.held_since_s = now_s
        self.last_q_ref: np.ndarray | None = None  # the reference in force (the rate cap's origin)
        # episodes this arm can never begin, and why (the node says so to the controller)
        self.refused: list[tuple[int, str]] = []

    @property
    def stopped(self) -> str | None:
        """Why the arm is stopped (an emergency stop or its own fault), or None."""
        return self.stop_latch.reason or self.fault

    def t_s(self, now: float) -> float:
        """Robot time: since the running episode began [s]."""
        return now - self.episode_t0_s

    # ---- what comes in -------------------------------------------------------------------
    def take_goal(self, start: Start, goal_m: tuple[float, float, float],
                  joint: JointState, now: float) -> str | None:  # fmt: skip
        """Begin homing to a new episode's start; why not now (the arm stopped: the
        episode waits for its release), or None (also for a repeat). An episode this arm
        can never begin is refused (``refused``) instead."""
        if start.episode == self.episode or (
            self.homing and self.homing.start.episode == start.episode
        ):
            return None  # a repeated announcement
        if start.episode == self.unreachable_episode:
            self.refused.append((start.episode, self.homing_failure or "unreachable"))
            return None
        if self.stopped is not None:
            return self.stopped
        violation = goal_violation(
            start.q_rad, goal_m, self.limits, self.layout, self.settings.limit_tolerance_rad
        )
        if violation is not None:
            self.refused.append((start.episode, violation))
            return None
        self.homing = self._plan_homing(start, joint.q_rad, now)
        self.command = self.held = None
        log.info("episode %d: moving to the start posture (%.1f s)", start.episode,
                 self.homing.duration_s)  # fmt: skip
        return None

    def take_command(self, command: CoreCommand, state_stamp_ns: int, joint: JointState,
                     now: float) -> str | None:  # fmt: skip
        """Apply the controller's command through the arm's caps; why not, or None."""
        reason = self.stopped or self.freshness.why_stale(state_stamp_ns)
        dt = self.freshness.allowance_s(state_stamp_ns, 2 * self.period_s)
        guarded = guard_command(command, joint.q_rad, self.last_q_ref, dt, self.limits, self.caps)
        reason = reason or (None if guarded.clamped else guarded.reason)
        if reason is not None or guarded.command is None:
            return reason or "rejected"
        if guarded.clamped and (line := self.freshness.clamp(guarded.reason, state_stamp_ns)):
            log.log(guarded.log_level, "%s", line)
        if self.held is not None:
            log.info("commands resumed: leaving the hold")
        self.command, self.held = guarded.command, None
        if self.homing is None:  # in force now: a second command this cycle moves from it
            self.last_q_ref = guarded.command.q_ref
        self.freshness.applied(state_stamp_ns)
        self.in_force_answers_ns = state_stamp_ns
        self.command_wall_s = now
        return None

    def check(self, joint: JointState, restart: Callable[[int], None]) -> bool:
        """Latch a fault on a drive's fault, a joint beyond its limits or its speed; restart
        a drive that cut its torque, and hold its joint where it is once it is back.
        Whether the arm must now stop (the caller applies the stop)."""
        faulted = {fault.joint for fault in joint.faults}
        for j in self.recovery.restarting - joint.restarting:  # read this cycle again
            if j in faulted:
                self.recovery.not_cleared(j)  # still latched: its restarts never took
            else:
                self._drive_back(j, joint)
        first = self.fault is None
        if joint.faults:
            self.fault = self.fault or "; ".join(f.what for f in joint.faults)
            for fault in joint.faults:
                if self.settings.stop_action == "hold" and self.recovery.fault(fault):
                    self._restart(fault.joint, restart)
                self._say(fault.joint, self.recovery.notes.get(fault.joint, fault.what))
        elif first:
            self.fault = limit_violation(
                self.limits, joint.q_rad, joint.dq_rad_s, self.settings.limit_tolerance_rad,
                self.settings.overspeed_stop_fraction / self.settings.speed_fraction,
            )  # fmt: skip
        if first and self.fault is not None:
            log.error("arm fault: %s: stopping", self.fault)
            return True
        return False

    def _restart(self, j: int, restart: Callable[[int], None]) -> None:
        """Restart joint ``j``'s drive; a restart that never went out (a bus error) counts
        for nothing and is sent again at the fault's next report, and the stop goes on
        (the error once left the joint off for good and the arm never stopped)."""
        try:
            restart(j)
        except DriverError as exc:
            self.recovery.not_sent(j)
            log.warning("joint %d's restart not sent (%s): sent again", j + 1, exc)

    def _say(self, joint: int, note: str) -> None:
        """A drive's news, logged once (a drive left off reports its fault every cycle)."""
        if self.said.get(joint) != note:
            self.said[joint] = note
            log.error("%s", note)

    def _drive_back(self, j: int, joint: JointState) -> None:
        """A restarted drive holds where its joint is now: the stop's law there too."""
        self.recovery.back(j, float(joint.q_rad[j]))
        log.warning("%s", self.recovery.notes[j])
        if self.held is not None:
            q_ref = self.held.q_ref.copy()
            q_ref[j] = joint.q_rad[j]
            self.held = self._hold_law(q_ref, self.held.kp, self.held.kd, self.held_since_s)

    # ---- the law -------------------------------------------------------------------------
    def stop_here(self, q: np.ndarray, now: float) -> None:
        """Hold where the arm is now, with the stop gains."""
        self.homing = self.command = None
        self.held = self._hold_law(q, np.array(self.settings.stop_kp_nm_per_rad),
                                   np.array(self.settings.stop_kd_nms_per_rad), now)  # fmt: skip

    def release_here(self, q: np.ndarray, now: float) -> None:
        """The stop released: the ordinary hold where the arm is now (its gains, not the
        stop's, which a person can push against); motion waits for the next command."""
        if self.held is not None and self.homing is None:
            kp, kd = self.settings.hold_kp_nm_per_rad, self.settings.hold_kd_nms_per_rad
            self.held = self._hold_law(q, np.array(kp), np.array(kd), now)

    def law(self, joint: JointState, now: float, ramp: float,
            say_silent: Callable[[], str]) -> DriveCommand:  # fmt: skip
        """The joint law to write this period (``ramp``: the soft start's share)."""
        if self.stopped is not None and self.held is None:
            self.stop_here(joint.q_rad, now)  # stopped while the bus was away: hold here
        if self.homing is not None:
            law = self._homing_law(joint, now)
        elif self.held is not None:
            law = self.held
        elif (
            self.command is not None and now - self.command_wall_s <= self.settings.command_stale_s
        ):
            law = self.command
        else:
            law = self.begin_hold(joint.q_rad, now, say_silent)
        self.last_q_ref = law.q_ref
        drive = DriveCommand(law.q_ref, law.dq_ref, law.tau_ff, law.kp, law.kd,
                             self.limits.tau_max)  # fmt: skip
        return softened(drive, ramp)

    def _stale(self, now: float) -> bool:
        return now - self.command_wall_s > self.settings.command_stale_s

    def after_stall(self, joint: JointState, now: float) -> None:
        """The drives had stopped themselves during a stall of this process (where they
        were, with the gains in force, the feed-forward gone: the arm sagged): hold where
        it is now, with the law's gains (a homing move starts again from there). Nothing
        resumes a motion, nor pulls back to a hold, planned before the stall. A start
        posture not reached before may have been theirs: its episode, announced again, is
        tried again."""
        self.unreachable_episode, self.homing_failure = -1, None  # they may be why: try again
        if self.homing is not None:
            self.homing = self._plan_homing(self.homing.start, joint.q_rad, now)
        elif self.held is not None:
            self.held = self._hold_law(joint.q_rad, self.held.kp, self.held.kd, now)
        else:
            self.begin_hold(joint.q_rad, now, None)  # this process stalled, not the controller

    def _plan_homing(self, start: Start, q: np.ndarray, now: float) -> Homing:
        return Homing.plan(start, q, self.settings.homing_speed_rad_s, now, self.max_step_s)

    def begin_hold(
        self, q: np.ndarray, now: float, say_silent: Callable[[], str] | None
    ) -> CoreCommand:
        """Commands went stale (or never came): hold here with the last command's gains;
        ``say_silent`` says what the controller is doing (None: not its fault)."""
        if self.command is not None and say_silent is not None:
            log.warning("no valid command from the controller (%s) for %.2f s: holding",
                        say_silent(), self.settings.command_stale_s)  # fmt: skip
        last = self.command
        kp = last.kp if last is not None else np.array(self.settings.hold_kp_nm_per_rad)
        kd = last.kd if last is not None else np.array(self.settings.hold_kd_nms_per_rad)
        self.command = None
        self.in_force_answers_ns = None
        self.held = self._hold_law(q, kp, kd, now)
        return self.held

    def forget_motion(self) -> None:
        """The bus was lost or came back: no command, homing or hold survives it."""
        self.command = self.homing = self.held = None

    def _hold_law(self, q: np.ndarray, kp: np.ndarray, kd: np.ndarray,
                  now: float) -> CoreCommand:  # fmt: skip
        self.held_since_s = now
        self.freshness.held(self.t_s(now))
        zeros = np.zeros(6)
        return CoreCommand(q.copy(), zeros, self.arm.inverse_dynamics(q, zeros, zeros), kp, kd)

    def _homing_law(self, joint: JointState, now: float) -> CoreCommand:
        homing = self.homing
        assert homing is not None
        q_ref, dq_ref = homing.reference(now)
        resting = float(np.max(np.abs(joint.dq_rad_s))) < self.settings.rest_speed_rad_s
        there = float(np.max(np.abs(joint.q_rad - homing.start.q_rad)))
        late = homing.since_end(now)
        if late >= 0 and resting and there < self.settings.homing_tolerance_rad:
            return self._begin_episode(homing.start, joint.q_rad, now)
        if late > self.settings.homing_timeout_s:
            return self._give_up_homing(homing, joint, now)
        # never farther from the arm than a command may be: an arm held back (by the person,
        # the table) and let go follows a reference at most this far ahead, not the whole way
        reach = self.caps.max_relative_target_rad
        near = np.clip(q_ref, joint.q_rad - reach, joint.q_rad + reach)
        dq_ref = np.where(near == q_ref, dq_ref, 0.0)
        q_ref = near
        gravity = self.arm.inverse_dynamics(q_ref, np.zeros(6), np.zeros(6))
        kp, kd = (
            np.array(self.settings.hold_kp_nm_per_rad),
            np.array(self.settings.hold_kd_nms_per_rad),
        )
        return CoreCommand(q_ref, dq_ref, gravity, kp, kd)

    def _give_up_homing(self, homing: Homing, joint: JointState, now: float) -> CoreCommand:
        """The start posture was not reached: refuse the episode, hold where the arm is."""
        miss = float(np.max(np.abs(joint.q_rad - homing.start.q_rad)))
        self.homing_failure = (
            f"episode {homing.start.episode}: the start posture not reached ({miss:.3f} rad "
            f"away {self.settings.homing_timeout_s:.1f} s after the move): holding"
        )
        log.error("%s", self.homing_failure)
        self.refused.append((homing.start.episode, self.homing_failure))
        self.unreachable_episode = homing.start.episode
        self.homing = None
        return self.begin_hold(joint.q_rad, now, None)

    def _begin_episode(self, start: Start, q: np.ndarray, now: float) -> CoreCommand:
        """The arm rests near its start: the episode begins, holding where the arm is (the
        controller's reach starts from the measured posture; a hold at the exact start
        would make its first command a jump for the rate cap)."""
        self.homing = None
        self.episode = start.episode
        self.episode_t0_s = now
        self.held = self._hold_law(q, np.array(self.settings.hold_kp_nm_per_rad),
                                   np.array(self.settings.hold_kd_nms_per_rad), now)  # fmt: skip
        log.info("episode %d: the arm rests at its start", start.episode)
        return self.held
