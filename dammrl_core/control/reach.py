"""One reach as the controller supervises it: the one copy of the per-tick logic.

The in-process runner and the controller node both drive a :class:`Reach` with the
states they receive, so a seed behaves the same in both compositions. One tick:

1. log the state;
2. end the reach on success (the button pressed and held for the dwell time) or at the
   episode timeout (the paper's criterion, ||x - x_g|| <= eps_g, is reported beside);
3. deliver the human's answer once the robot clock reaches its due time (the request
   time plus the time the human took), with the step vector j chosen for it;
4. ask for a new decision when the controller wants one and none is outstanding;
5. tick the controller (trigger, micro-step, IK, reference) for the joint command.

Who answers a request (a simulated human in-process, the intent and policy services on
the bus) is the composition's business: it calls :meth:`Reach.answer`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dammrl_core.control.controller import Controller, Early, ReferenceInputs, first_true
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.dynamics import ArmModel
from dammrl_core.ik import IKSolver
from dammrl_core.metrics import Dwell, ReachMetrics, goal_error, reach_metrics
from dammrl_core.robot import RobotDescription
from dammrl_core.robot.scene import SENSOR_LAYOUT
from dammrl_core.state import Intent, JointCommand, RobotState, StepEvent
from dammrl_core.task import (
    ReachTask,
    SeedStreams,
    TaskSettings,
    seed_streams,
    start_posture,
    task_for_seed,
)

HOLD_OBSERVATION_S = 0.5  # the in-process runner logs this long after a hold (plots)
DUE_TOLERANCE_S = 1e-9  # robot-clock rounding when comparing a tick with a due time


@dataclass(frozen=True)
class Trajectory:
    """Uniformly sampled log of one reach (control rate)."""

    t: np.ndarray  # (N,) [s]
    x: np.ndarray  # end-effector position (N, 3) [m]
    v: np.ndarray  # end-effector velocity (N, 3) [m/s]
    q: np.ndarray  # joint positions (N, 6) [rad]
    tau: np.ndarray  # applied torques (N, 6) [N m]
    subgoal: np.ndarray  # active subgoal (N, 3) [m], NaN before the first step
    radius: np.ndarray  # active admission radius (N,) [m]
    x_true: np.ndarray  # noise-free end-effector position (N, 3) [m], NaN where unknown


class ReachLog:
    """Preallocated log of every tick (one row per control period)."""

    COLUMNS: ClassVar[dict[str, tuple[int, int]]] = {
        "x": (0, 3), "v": (3, 6), "q": (6, 12), "tau": (12, 18), "subgoal": (18, 21),
        "x_true": (23, 26),
    }  # fmt: skip
    RADIUS, TIME, WIDTH = 21, 22, 26

    def __init__(self, capacity: int) -> None:
        self.rows = np.full((capacity, self.WIDTH), np.nan)
        self.n = 0
        self.button_pressed = False

    def record(self, state: RobotState, subgoal: np.ndarray | None, radius_m: float) -> None:
        self._grow(1)
        row = self.rows[self.n]
        row[0:3], row[3:6], row[6:12], row[12:18] = state.ee_pos, state.ee_vel, state.q, state.tau
        row[18:21] = subgoal if subgoal is not None else np.nan
        row[self.RADIUS], row[self.TIME] = radius_m, state.t_s
        row[23:26] = state.ee_pos_true if state.ee_pos_true is not None else np.nan
        self.n += 1
        self.button_pressed |= state.button_pressed

    def record_many(
        self,
        times: np.ndarray,
        sensors: np.ndarray,
        subgoal: np.ndarray | None,
        radius_m: float,
        press_travel_m: float,
        true_ee: np.ndarray | None = None,
    ) -> None:
        """Log many ticks at once from raw sensor rows (see SENSOR_LAYOUT) and, when known,
        the noise-free end-effector positions (n, 3)."""
        if len(times) == 0:
            return
        self._grow(len(times))
        block = self.rows[self.n : self.n + len(times)]
        for name, key in (("x", "ee_pos"), ("v", "ee_vel"), ("q", "q"), ("tau", "tau")):
            lo, hi = self.COLUMNS[name]
            block[:, lo:hi] = sensors[:, SENSOR_LAYOUT[key]]
        block[:, 18:21] = subgoal if subgoal is not None else np.nan
        block[:, self.RADIUS], block[:, self.TIME] = radius_m, times
        block[:, 23:26] = true_ee if true_ee is not None else np.nan
        self.n += len(times)
        travel = -sensors[:, SENSOR_LAYOUT["button"]][:, 0]
        self.button_pressed |= bool(np.any(travel >= press_travel_m))

    @property
    def last_t_s(self) -> float:
        """Time of the last logged tick [s] (0 before any)."""
        return float(self.rows[self.n - 1, self.TIME]) if self.n else 0.0

    def trajectory(self, start: int = 0, until_s: float = np.inf) -> Trajectory:
        """Rows from ``start`` on, up to the time ``until_s``."""
        log = self.rows[start : self.n]
        log = log[log[:, self.TIME] <= until_s + DUE_TOLERANCE_S]
        columns = {name: log[:, lo:hi].copy() for name, (lo, hi) in self.COLUMNS.items()}
        return Trajectory(t=log[:, self.TIME].copy(), radius=log[:, self.RADIUS].copy(), **columns)

    def _grow(self, rows: int) -> None:
        if self.n + rows > len(self.rows):
            extra = np.full((max(rows, len(self.rows)), self.WIDTH), np.nan)
            self.rows = np.vstack([self.rows, extra])


@dataclass(frozen=True)
class Tick:
    """What one tick asks of the composition."""

    command: JointCommand | None  # send to the arm (None: the reach ended at this state)
    steps: list[StepEvent]  # micro-steps whose reference started at this tick
    ask: bool  # request a human decision now (answer with Reach.answer)
    ended: tuple[str, str] | None  # (outcome, reason) when the reach ended at this tick


@dataclass(frozen=True)
class Answer:
    """The human's decision for the open request and the step vector chosen with it."""

    intent: Intent  # intent.t_s: when it is due on the robot clock [s]
    steps_m: np.ndarray | None  # delta (3,) [m] of the model choice; None: keep the current
    correct: bool | None  # toward the goal (a simulated human knows; a person is scored)


class Reach:
    """The supervisor of one reach: the controller core plus success, timeout, decisions."""

    def __init__(
        self, controller: Controller, task: ReachTask, settings: TaskSettings, control_dt_s: float
    ) -> None:
        self.controller = controller
        self.task = task
        self.timeout_s = settings.episode_timeout_s
        self.tolerance_m = settings.goal_tolerance_m
        self.pressed = Dwell(settings.goal_dwell_s)  # success: the button pressed and held
        capacity = int((settings.episode_timeout_s + HOLD_OBSERVATION_S) / control_dt_s) + 4
        self.log = ReachLog(capacity)
        self.steps: list[StepEvent] = []
        self.answers: list[Answer] = []  # every decision delivered or pending
        self.pending: Answer | None = None  # the answer waiting for its due time
        self.asked = False  # a request is out and not yet answered
        self.started = False
        self.ended: tuple[str, str] | None = None
        self.end_s: float | None = None  # when the reach ended (a hold: when it began)

    # ---- the composition's calls ------------------------------------------------
    def tick(self, state: RobotState, early: Early | None = None) -> Tick:
        """One control period at ``state``; ``early`` may get its command before the tick
        ends (``Controller.tick``), never on a tick that asks (lockstep holds its command
        back for the answer)."""
        if not self.started:
            self.controller.reset(state, self.task.goal)
            self.started = True
        self._record(state)
        if self.ended is None and (ended := self._judge(state)) is not None:
            self._end(ended, state.t_s)
            return Tick(None, [], False, ended)
        self._deliver_due(state.t_s)
        ask = self.ended is None and self._wants_decision()
        self.asked |= ask
        output = self.controller.tick(state, None if ask else early)
        self.steps.extend(output.steps)
        ended = None
        if output.hold_reason is not None and self.ended is None:
            ended = ("hold", output.hold_reason)
            self._end(ended, state.t_s)
        return Tick(output.command, output.steps, ask, ended)

    def observe(self, state: RobotState) -> tuple[str, str] | None:
        """A state a newer one superseded before it was answered (the composition ran
        late): logged and judged like a tick, but no command (the newest state gets the
        command, planned from where the arm is). The end, if the reach ended there."""
        if not self.started:
            return None  # the reach starts at the first state it answers
        self._record(state)
        if self.ended is None and (ended := self._judge(state)) is not None:
            self._end(ended, state.t_s)
            return ended
        return None

    def answer(self, answer: Answer) -> None:
        """The human's decision for the open request; delivered when due."""
        self.pending = answer
        self.answers.append(answer)
        self.asked = False

    def end(self, outcome: str, reason: str, t_s: float) -> None:
        """End the reach from outside (the bus: stale state, a stop); the arm holds."""
        if self.ended is None:
            self._end((outcome, reason), t_s)

    # ---- quiet ticks in bulk (the in-process runner) ---------------------------------
    @property
    def coasting(self) -> bool:
        """The coming ticks would only log their state and command the reference until a
        state brings an event (``first_event``): a running reach, no press being held, no
        decision to ask for, and the controller coasting."""
        return (
            self.started
            and self.ended is None
            and not self.dwelling
            and not self._wants_decision()
            and self.controller.coasting
        )

    def first_event(
        self, times: np.ndarray, rows: np.ndarray, press_travel_m: float, inputs: ReferenceInputs
    ) -> int:
        """The first of these states (times (n,), sensor rows (n, k) as the arm reads them,
        see SENSOR_LAYOUT), ticked with the controller's ``inputs``, at which ``tick`` would
        do more than log it and command the reference: the button pressed, the timeout, a
        decision due, or the controller's own events; n: none."""
        travel = -rows[:, SENSOR_LAYOUT["button"]][:, 0]
        eventful = (travel >= press_travel_m) | (times >= self.timeout_s)
        if self.pending is not None:
            eventful |= times >= self.pending.intent.t_s - DUE_TOLERANCE_S
        first = first_true(eventful)
        column = {k: rows[:first, SENSOR_LAYOUT[k]] for k in ("q", "dq", "ee_pos", "ee_vel")}
        return self.controller.first_event(times[:first], column["q"], column["dq"],
                                           column["ee_pos"], column["ee_vel"], inputs)  # fmt: skip

    def coast(
        self,
        times: np.ndarray,
        rows: np.ndarray,
        true_ee: np.ndarray,
        press_travel_m: float,
        inputs: ReferenceInputs,
    ) -> JointCommand | None:
        """These states (before ``first_event``) ran as quiet ticks with the controller's
        ``inputs``: logged as ``tick`` logs them (a step's start logs the subgoal it
        replaces), its step kept; the command of the last (None: none ran)."""
        controller, n = self.controller, len(times)
        before = min(inputs.start + 1, n)
        self.log.record_many(times[:before], rows[:before], controller.subgoal,
                             controller.radius_m, press_travel_m, true_ee[:before])  # fmt: skip
        command, started = controller.settle(inputs, n)
        self.steps.extend(started)
        self.log.record_many(times[before:], rows[before:], controller.subgoal,
                             controller.radius_m, press_travel_m, true_ee[before:])  # fmt: skip
        return command

    # ---- results ------------------------------------------------------------------
    def metrics(self) -> ReachMetrics:
        """The metrics of the reach up to its end (a hold counts from its start)."""
        outcome, reason = self.ended or ("timeout", "episode timeout")
        t_end = (
            self.end_s
            if self.end_s is not None
            else float(self.log.rows[self.log.n - 1, ReachLog.TIME])
        )
        traj = self.log.trajectory(until_s=t_end)
        x = traj.x if len(traj.x) else self.task.start[None, :]
        due = [a for a in self.answers if a.intent.t_s <= t_end + DUE_TOLERANCE_S]
        return reach_metrics(
            outcome=outcome,
            reason=reason,
            t_end_s=t_end,
            t=traj.t,
            x=x,
            v=traj.v,
            goal=self.task.goal,
            subgoals=np.array([s.subgoal for s in self.steps]),
            radii=np.array([s.radius_m for s in self.steps]),
            decisions_correct=[bool(a.correct) for a in due if a.correct is not None],
            button_pressed=self.log.button_pressed,
            reached=bool(np.any(goal_error(x, self.task.goal) <= self.tolerance_m)),
        )

    # ---- inside a tick --------------------------------------------------------------
    @property
    def dwelling(self) -> bool:
        """A success may be due within the dwell time."""
        return self.pressed.entered_s is not None

    def _record(self, state: RobotState) -> None:
        self.log.record(state, self.controller.subgoal, self.controller.radius_m)

    def _judge(self, state: RobotState) -> tuple[str, str] | None:
        if self.pressed.update(state.t_s, state.button_pressed):
            return "success", "button pressed"
        if state.t_s >= self.timeout_s:
            return "timeout", "episode timeout"
        return None

    def _deliver_due(self, t_s: float) -> None:
        pending = self.pending
        if pending is not None and t_s >= pending.intent.t_s - DUE_TOLERANCE_S:
            if pending.steps_m is not None:
                self.controller.set_steps(pending.steps_m)
            self.controller.on_intent(pending.intent)
            self.pending = None

    def _wants_decision(self) -> bool:
        return not self.asked and self.pending is None and self.controller.wants_intent

    def _end(self, ended: tuple[str, str], t_s: float) -> None:
        self.ended, self.end_s = ended, t_s
        self.controller.hold(ended[1], t_s)


@dataclass(frozen=True)
class Plan:
    """One episode of a seed, ready to run in any composition."""

    seed: int
    task: ReachTask
    q_start: np.ndarray  # the start posture (6,) [rad]
    reach: Reach
    streams: SeedStreams  # the seed's named random streams (human, simulated arm, ...)


def plan_reach(
    seed: int,
    controller: ControllerSettings,
    task_settings: TaskSettings,
    robot: RobotDescription,
    arm: ArmModel,
    ik: IKSolver,
    control_dt_s: float,
    task: ReachTask | None = None,
) -> Plan:
    """The task, start posture and supervised controller of ``seed`` (the one definition the
    in-process runner and the controller service share)."""
    streams = seed_streams(seed)
    task = task or task_for_seed(task_settings, seed)
    q_start = start_posture(arm, task_settings, task.start)
    core = Controller(robot, controller, streams.ik_latency, arm, ik)
    return Plan(seed, task, q_start, Reach(core, task, task_settings, control_dt_s), streams)
