"""The controller core: intent + model choice + state -> micro-steps -> joint commands.

Pure logic: no bus, no clock. It is handed the robot state (whose ``t_s`` is the time)
and the human's intents, and returns joint commands plus what happened (steps, decision
requests, holds). The in-process runner and the bus node both drive this one object.

Timeline of one event-triggered step: the trigger fires (||x - x_m|| <= eps, dV/dt <= 0)
-> a decision is requested -> the intent arrives -> dx (eq. 2), IK -> after the IK
latency the new joint reference starts -> ... -> the trigger fires again. The
fixed-frequency baseline instead plans a step every ``fixed_period_s`` with the latest
intent, wherever the arm is.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from dammrl_core import safety
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.control.stepping import event_trigger, fixed_timer_due, micro_step
from dammrl_core.control.trajectory import QuinticSegment, segment_duration
from dammrl_core.dynamics import ArmModel, joint_limit_avoidance
from dammrl_core.ik import IKLatency, IKSolver, make_ik_solver
from dammrl_core.robot import RobotDescription
from dammrl_core.state import Intent, JointCommand, RobotState, StepEvent

Early = Callable[[JointCommand], None]
"""Takes a tick's command ahead of the tick's end (``Controller.tick``)."""


@dataclass
class ControllerOutput:
    command: JointCommand
    steps: list[StepEvent] = field(default_factory=list)  # steps that started their reference
    hold_reason: str | None = None  # set on the tick the controller entered a hold


@dataclass(frozen=True)
class ReferenceInputs:
    """The commands ``Controller.tick`` returns at a run of quiet ticks (rows): the
    reference and the feedforward, (n, n_joints) each; ``resting``: the ticks at which the
    reference rests (the controller then re-sends one command object). A step whose solve
    is waiting out its latency starts at tick ``start`` (n: none in these ticks) with the
    reference ``started``; the rows from there on are that reference's."""

    q_ref: np.ndarray
    dq_ref: np.ndarray
    tau_ff: np.ndarray
    resting: np.ndarray  # (n,) bool
    start: int
    started: QuinticSegment | None


@dataclass(frozen=True)
class _PlannedStep:
    ready_s: float  # when the IK result becomes available
    q_target: np.ndarray
    event: StepEvent
    # planned from a resting reference: (that reference, the step's own from there, as if
    # started at the plan's tick); from the same rest, a later start only moves it in time
    from_rest: tuple[QuinticSegment, QuinticSegment] | None = None


def first_true(flags: np.ndarray) -> int:
    """The index of the first true of ``flags`` (n,); n when none."""
    n = len(flags)
    first = int(flags.argmax()) if n else 0  # the method: np.argmax wraps it in Python
    return first if n and flags[first] else n


def latency_model(
    settings: ControllerSettings, rng: np.random.Generator, replay: Sequence[float] | None = None
) -> IKLatency:
    """The IK latency the settings ask for (``replay``: a run's, again). A drawn latency
    ('model') follows the profile's distribution; a reference one charges the solver that
    runs (its work is what the reference machine timed)."""
    charged = settings.ik_solver if settings.ik_latency == "reference" else (
        settings.ik_latency_profile)  # fmt: skip
    return IKLatency(
        settings.ik_latency,
        charged,
        rng,
        settings.ik_latency_median_s,
        settings.ik_latency_sigma,
        replay,
        settings.ik_latency_scale,
    )


class Controller:
    """Event-triggered (or fixed-rate) micro-step controller of one reach."""

    def __init__(
        self,
        robot: RobotDescription,
        settings: ControllerSettings,
        rng: np.random.Generator,
        arm: ArmModel | None = None,
        ik: IKSolver | None = None,
        latency: IKLatency | None = None,
    ) -> None:
        """``latency`` (default: the settings' model on ``rng``): a prepared one, such as a
        replay of a measured run's latencies."""
        self.robot = robot
        self.settings = settings
        self.arm = arm or ArmModel(robot)
        self.ik = ik or make_ik_solver(
            settings.ik_solver,
            self.arm,
            settings.joint_limit_margin_rad,
            settings.max_joint_step_rad,
        )
        self.latency = latency or latency_model(settings, rng)
        self.kp = np.array(settings.kp, dtype=float)
        self.kd = np.array(settings.kd, dtype=float)
        self.weights = np.array(settings.lyapunov_weights, dtype=float)
        self.workspace = (
            np.array(settings.workspace_min_m, dtype=float),
            np.array(settings.workspace_max_m, dtype=float),
        )
        self.steps_m = np.full(3, 0.01)
        self.goal = np.zeros(3)
        self.segment = QuinticSegment.hold(0.0, np.zeros(6))
        self._rest_command: JointCommand | None = None
        self._rest_segment: QuinticSegment | None = None
        self.limits = safety.LimitMonitor(robot)
        self.intent: Intent | None = None  # latest undelivered (event) / sampled (fixed) decision
        self.planned: list[_PlannedStep] = []  # solved steps waiting out their IK latency
        self.subgoal: np.ndarray | None = None  # x_m, the active Cartesian subgoal (3,) [m]
        self.radius_m = 0.0  # admission radius of the active step [m]
        self.awaiting_trigger = False
        self.last_step_s: float | None = None  # fixed-rate: time of the last timer tick
        self.hold_reason: str | None = None
        self.index = 0

    # ---- inputs -------------------------------------------------------------------
    def reset(self, state: RobotState, goal: np.ndarray) -> JointCommand:
        """Start a reach to ``goal`` [m] from the arm at rest in ``state``."""
        self.goal = np.asarray(goal, dtype=float)
        self.segment = QuinticSegment.hold(state.t_s, state.q.copy())
        self._reset_episode_state()
        return self._command(state)

    def set_steps(self, steps_m: np.ndarray) -> None:
        """Robot model choice: the step magnitudes delta (3,) [m] for the next steps."""
        steps = np.asarray(steps_m, dtype=float)
        if steps.shape != (3,) or not np.all(np.isfinite(steps)) or np.any(steps <= 0):
            raise ValueError(f"step magnitudes must be 3 positive numbers [m], got {steps_m}")
        self.steps_m = steps

    def on_intent(self, intent: Intent) -> None:
        """A decision of the human; the latest one is used for the next step."""
        self.intent = intent

    def hold(self, reason: str, t_s: float) -> None:
        """Stop stepping; the reference stays where it is at ``t_s``."""
        if self.hold_reason is None:
            self.hold_reason = reason
            q, _, _ = self.segment.sample(t_s)
            self.segment = QuinticSegment.hold(t_s, q)
            self.planned.clear()

    @property
    def wants_intent(self) -> bool:
        """True while the controller is waiting for (or, fixed-rate, sampling) decisions."""
        if self.hold_reason is not None:
            return False
        if self.settings.trigger == "fixed":  # latest: always deciding; fresh: one per step
            return self.settings.fixed_decisions == "latest" or self.intent is None
        return self.intent is None and not self.planned and not self.awaiting_trigger

    @property
    def idle(self) -> bool:
        """Nothing changes until a new intent arrives: the controller holds, or (event mode)
        its trigger has fired, no solve is pending and its reference rests with a fixed
        command. Each tick would only re-check the limits and return the same command."""
        if self.hold_reason is not None:
            return True
        return (
            self.settings.trigger == "event"
            and self.settings.feedforward == "inverse_dynamics"
            and self.intent is None
            and not self.planned
            and not self.awaiting_trigger
            and self._rest_command is not None
            and self._rest_segment is self.segment
        )

    # ---- the control tick ---------------------------------------------------------
    def tick(self, state: RobotState, early: Early | None = None) -> ControllerOutput:
        """One control period: progression logic, then the joint command for ``state``.

        A step planned from a resting reference (event mode) is planned after its tick's
        command: the rest command, which the plan cannot change (a hold, or a step started
        at once, begins where the reference rests). ``early`` gets that command before the
        plan's IK runs: the bus sends it to the arm first."""
        started: list[StepEvent] = []
        entered_hold = self.hold_reason
        command = None
        if self.hold_reason is None:
            command = self._progress(state, started, early)
        reason = self.hold_reason if entered_hold is None else None
        return ControllerOutput(
            self._command(state) if command is None else command, started, reason
        )

    def _progress(
        self, state: RobotState, started: list[StepEvent], early: Early | None
    ) -> JointCommand | None:
        t = state.t_s
        violation = self.limits.check(state.q, state.dq)
        if violation is not None:
            self.hold(violation, t)
            return None
        self._start_if_ready(t, started)  # a solve that finished since the last tick
        command = None
        if self.settings.trigger == "event":
            command = self._event_progress(state, early)
        else:
            self._fixed_progress(state)
        self._start_if_ready(t, started)  # a step planned now with no IK latency
        return command

    def _start_if_ready(self, t: float, started: list[StepEvent]) -> None:
        while self.planned and t >= self.planned[0].ready_s:
            started.append(self._start_segment(self.planned.pop(0), t))

    def _event_progress(self, state: RobotState, early: Early | None) -> JointCommand | None:
        """Check the armed trigger, or plan the next step; the tick's command when it was
        made before the plan (see ``tick``)."""
        t = state.t_s
        if self.awaiting_trigger and self.subgoal is not None:
            if event_trigger(state.ee_pos, state.ee_vel, self.subgoal, self.radius_m, self.weights):
                self.awaiting_trigger = False
            elif t - self.segment.t0_s > self.settings.trigger_timeout_s:
                self.hold(
                    f"no trigger within {self.settings.trigger_timeout_s:.1f} s: end-effector "
                    f"{np.linalg.norm(self.subgoal - state.ee_pos) * 1000:.1f} mm from its subgoal",
                    t,
                )
            return None
        if self.planned or self.intent is None:
            return None
        intent, self.intent = self.intent, None  # each decision drives one step
        command = self._command(state) if self.segment.finished(t) else None
        if command is not None and early is not None:
            early(command)
        self._plan(state, intent)
        return command

    def _fixed_progress(self, state: RobotState) -> None:
        """Plan a step on every timer tick with the latest (or a fresh) intent, wherever
        the arm is."""
        t = state.t_s
        if self.intent is None:
            return  # no decision yet (or, fresh decisions, none since the last step)
        if self.planned and not self.settings.fixed_replan_while_pending:
            return  # the previous solve still running: this tick is late
        if fixed_timer_due(t, self.last_step_s, self.settings.fixed_period_s):
            self.last_step_s = t if self.last_step_s is None else self._next_tick(t)
            self._plan(state, self.intent)
            if self.settings.fixed_decisions == "fresh":
                self.intent = None

    def _next_tick(self, t: float) -> float:
        assert self.last_step_s is not None
        period = self.settings.fixed_period_s
        return self.last_step_s + period * math.floor((t - self.last_step_s) / period + 1e-9)

    # ---- planning -----------------------------------------------------------------
    def _plan(self, state: RobotState, intent: Intent) -> None:
        """Micro-step from where the step starts, IK, and schedule it after the latency."""
        t, x = state.t_s, self._step_start(state)
        dx = micro_step(
            self.goal - x,
            intent.u_h,
            self.steps_m,
            self.settings.primary_axis,
            self.settings.orthogonal_deadband,
        )
        subgoal = x + dx
        reason = safety.outside_workspace(subgoal, *self.workspace)
        if reason is not None:
            self.hold(reason, t)
            return
        q_seed, _, _ = self.segment.sample(t)
        target = subgoal - self._calibration_offset(state)
        result = self.ik.solve(target, q_seed)
        reason = self._ik_refusal(target, q_seed, result.q, result.error_m)
        if reason is not None:
            self.hold(reason, t)
            return
        latency = self.latency(result.cpu_s, result.evaluations)
        self.index += 1
        event = StepEvent(
            index=self.index,
            t_s=t,
            start_s=t + latency,
            trigger=self.settings.trigger,
            u_h=intent.u_h,
            radius_m=intent.radius_m,
            steps_m=self.steps_m.copy(),
            dx=dx,
            x_start=x.copy(),
            subgoal=subgoal,
            goal_error_m=float(np.linalg.norm(self.goal - x)),
            ik_compute_s=result.compute_s,
            ik_latency_s=latency,
        )
        planned = _PlannedStep(t + latency, result.q, event)
        if self.segment.finished(t):  # its reference now, off the tick that starts it
            planned = replace(planned, from_rest=(self.segment, self._segment_from(planned, t)))
        self.planned.append(planned)
        self.radius_m = intent.radius_m

    def _calibration_offset(self, state: RobotState) -> np.ndarray:
        """Where the measured end-effector is relative to the nominal model's forward
        kinematics at the measured joint angles. A real arm's calibration error (link
        lengths, encoder zeros) shifts every IK solution by about this much; it changes
        slowly with the posture, so aiming at subgoal - offset lands on the subgoal."""
        if not self.settings.calibration_correction:
            return np.zeros(3)
        return np.asarray(state.ee_pos - self.arm.ee_position(state.q))

    def _step_start(self, state: RobotState) -> np.ndarray:
        """The measured position, or (fixed rate, the paper's chain) the last subgoal."""
        if self.settings.trigger == "fixed" and self.settings.fixed_step_from == "subgoal":
            if self.planned:
                return self.planned[-1].event.subgoal
            if self.subgoal is not None:
                return self.subgoal
        return state.ee_pos

    def _ik_refusal(
        self, target: np.ndarray, q_seed: np.ndarray, q: np.ndarray, error_m: float
    ) -> str | None:
        if error_m > self.settings.ik_accept_error_m or not np.all(np.isfinite(q)):
            return (
                f"IK did not converge ({self.ik.name}): best solution {error_m * 1000:.1f} mm "
                f"from target {np.round(target, 3).tolist()} m (unreachable?)"
            )
        jump = float(np.max(np.abs(q - q_seed)))
        if jump > self.settings.max_joint_step_rad + 1e-6:
            return f"IK solution jumps {jump:.2f} rad (> {self.settings.max_joint_step_rad} rad)"
        return None

    def _start_segment(self, planned: _PlannedStep, t: float) -> StepEvent:
        return self._begin(planned, self._segment_from(planned, t))

    def _segment_from(self, planned: _PlannedStep, t: float) -> QuinticSegment:
        """The reference of a step started at ``t``: from where the current one is then."""
        if planned.from_rest is not None and planned.from_rest[0] is self.segment:
            return planned.from_rest[1].moved_to(t)
        q0, v0, a0 = self.segment.sample(t)
        return QuinticSegment.plan(t, self._duration(planned, q0), q0, v0, a0, planned.q_target)

    def _duration(self, planned: _PlannedStep, q0: np.ndarray) -> float:
        return segment_duration(
            planned.q_target - q0,
            float(np.linalg.norm(planned.event.dx)),
            self.robot.dq_max,
            self.settings.joint_speed_fraction,
            self.settings.peak_speed_m_per_s,
            self.settings.min_segment_s,
        )

    def _begin(self, planned: _PlannedStep, segment: QuinticSegment) -> StepEvent:
        self.segment = segment
        self.subgoal = planned.event.subgoal
        self.awaiting_trigger = self.settings.trigger == "event"
        return planned.event

    # ---- quiet ticks, in bulk (the in-process runner) --------------------------------
    @property
    def coasting(self) -> bool:
        """Until a state brings an event (``first_event``), every tick would only check the
        state and command the reference at its time (``reference_inputs``): the event
        trigger, the inverse-dynamics feedforward (the command is a function of time), no
        hold, and no decision waiting to be planned."""
        return (
            self.hold_reason is None
            and self.settings.trigger == "event"
            and self.settings.feedforward == "inverse_dynamics"
            and (self.awaiting_trigger or bool(self.planned) or self.intent is None)
        )

    def first_event(
        self,
        times: np.ndarray,
        q: np.ndarray,
        dq: np.ndarray,
        ee_pos: np.ndarray,
        ee_vel: np.ndarray,
        inputs: ReferenceInputs,
    ) -> int:
        """The first of these states (rows: times (n,), the rest (n, k)), ticked with
        ``inputs``, at which ``tick`` would do more than command the reference (and start a
        planned step): a limit broken, the trigger fired or timed out; n when none. The
        same tests as ``tick``: what bulk arithmetic finds near the admission sphere is
        confirmed with the tick's own."""
        limits, either = self.limits, np.logical_or.reduce  # ndarray.any: a slow wrapper
        eventful = either(np.abs(q - limits.q_mid) > limits.q_half_span, axis=1)
        eventful |= either(np.abs(dq) > limits.dq_max, axis=1)
        first = first_true(eventful)
        armed = self.armed_trigger(inputs)
        if armed is None:
            return first
        subgoal, radius_m, since = armed
        # armed either by the reference in force or by the started one: a planned step and
        # an armed trigger never coexist (the trigger fires before a step is planned)
        t0_s = self.segment.t0_s if inputs.started is None else inputs.started.t0_s
        late = (times[since:] - t0_s) > self.settings.trigger_timeout_s
        first = min(first, since + first_true(late))
        error = subgoal - ee_pos[since:first]
        # a few ulps from the tick's own sum of squares at most: only these may be inside
        near = np.sum(error * error, axis=1) <= radius_m**2 * (1 + 1e-9)
        for k in since + np.flatnonzero(near):
            if event_trigger(ee_pos[k], ee_vel[k], subgoal, radius_m, self.weights):
                return int(k)
        return first

    def armed_trigger(self, inputs: ReferenceInputs) -> tuple[np.ndarray, float, int] | None:
        """Where the event trigger watches in the ticks of ``inputs``: (subgoal, admission
        radius [m], the first tick it watches), None where it does not."""
        if self.awaiting_trigger and self.subgoal is not None:
            return self.subgoal, self.radius_m, 0
        if inputs.started is not None and self.settings.trigger == "event":
            return self.planned[0].event.subgoal, self.radius_m, inputs.start
        return None

    def foreseen_end_s(self) -> float:
        """About when the planned step's reference comes to rest, were it started at its
        ready time (how far ahead quiet ticks are worth foreseeing; never a result)."""
        planned = self.planned[0]
        q0, _, _ = self.segment.sample(planned.ready_s)
        return planned.ready_s + self._duration(planned, q0)

    def reference_inputs(self, times: np.ndarray) -> ReferenceInputs:
        """The commands ``tick`` returns at these times (increasing) while ``coasting``,
        a planned step started at the first of them from its ready time on (changing
        nothing: ``settle`` takes the ticks that ran)."""
        start, started = len(times), None
        if self.planned:
            start = int(np.searchsorted(times, self.planned[0].ready_s))
            if start < len(times):
                started = self._segment_from(self.planned[0], float(times[start]))
        q_ref, dq_ref, tau, resting = self._segment_inputs(self.segment, times[:start])
        if started is not None:
            rows = zip((q_ref, dq_ref, tau, resting),
                       self._segment_inputs(started, times[start:]), strict=True)  # fmt: skip
            q_ref, dq_ref, tau, resting = (np.concatenate(pair) for pair in rows)
        tau = safety.saturate_torque(tau, self.robot.tau_max)  # elementwise, as per tick
        return ReferenceInputs(q_ref, dq_ref, tau, resting, start, started)

    def _segment_inputs(
        self, segment: QuinticSegment, times: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(q_ref, dq_ref, unsaturated tau_ff, resting) of ``segment`` at these times."""
        q_ref, dq_ref, ddq_ref = segment.sample_many(times)
        resting = times >= segment.t0_s + segment.duration_s
        moving = first_true(resting)
        tau = np.empty_like(q_ref)
        tau[:moving] = self.arm.inverse_dynamics_many(
            q_ref[:moving], dq_ref[:moving], ddq_ref[:moving]
        )
        if moving < len(times):  # the same reference at rest: the same torque
            cached = self._rest_command is not None and self._rest_segment is segment
            if cached and self._rest_command is not None:
                tau[moving:] = self._rest_command.tau_ff
            else:
                dynamics = self.arm.inverse_dynamics
                tau[moving:] = dynamics(q_ref[moving], dq_ref[moving], ddq_ref[moving])
        return q_ref, dq_ref, tau, resting

    def settle(
        self, inputs: ReferenceInputs, ran: int
    ) -> tuple[JointCommand | None, list[StepEvent]]:
        """The first ``ran`` of ``inputs`` ran as ticks: the command of the last one
        (None: none ran), keeping the resting command as ``tick`` does, and the step they
        started (as ``tick`` reports it)."""
        started = []
        if inputs.started is not None and inputs.start < ran:
            started.append(self._begin(self.planned.pop(0), inputs.started))
        if ran == 0:
            return None, started
        k = ran - 1
        if not inputs.resting[k]:
            command = JointCommand(inputs.q_ref[k], inputs.dq_ref[k], inputs.tau_ff[k],
                                   self.kp, self.kd)  # fmt: skip
            return command, started
        if self._rest_command is None or self._rest_segment is not self.segment:
            q, dq, _ = self.segment.rest
            command = JointCommand(q, dq, inputs.tau_ff[k], self.kp, self.kd)
            self._rest_command, self._rest_segment = command, self.segment
        return self._rest_command, started

    # ---- command ------------------------------------------------------------------
    def rehearse(self, state: RobotState) -> None:
        """A quiet tick's arithmetic on ``state`` (its limits, trigger, reference and
        torques), every result dropped and nothing kept: the bus runs it while it waits
        for the next state, and that tick then finds its code and data warm
        (``services.common.bus.Bus.rehearse``)."""
        self.limits.check(state.q, state.dq)
        if self.subgoal is not None:
            event_trigger(state.ee_pos, state.ee_vel, self.subgoal, self.radius_m, self.weights)
        q_ref, dq_ref, ddq_ref = self.segment.sample(state.t_s)
        if self.settings.feedforward == "resolved_acceleration":
            self._resolved_acceleration_torque(state, q_ref, dq_ref, ddq_ref)
        else:
            self.arm.inverse_dynamics(q_ref, dq_ref, ddq_ref)

    def _command(self, state: RobotState) -> JointCommand:
        resting = self.segment.finished(state.t_s)
        static = resting and self.settings.feedforward == "inverse_dynamics"
        if static and self._rest_command is not None and self._rest_segment is self.segment:
            return self._rest_command  # same object: the sim keeps its latched command
        q_ref, dq_ref, ddq_ref = self.segment.sample(state.t_s)
        if self.settings.feedforward == "resolved_acceleration":
            tau = self._resolved_acceleration_torque(state, q_ref, dq_ref, ddq_ref)
        else:
            tau = self.arm.inverse_dynamics(q_ref, dq_ref, ddq_ref)
        tau = safety.saturate_torque(tau, self.robot.tau_max)
        command = JointCommand(q_ref, dq_ref, tau, self.kp, self.kd)
        if static:
            self._rest_command, self._rest_segment = command, self.segment
        return command

    def _resolved_acceleration_torque(
        self, state: RobotState, q_ref: np.ndarray, dq_ref: np.ndarray, ddq_ref: np.ndarray
    ) -> np.ndarray:
        """Computed torque with the paper's resolved acceleration at the measured state.

        The desired end-effector acceleration is the one the joint reference implies
        (J ddq_ref + Jdot dq_ref at the reference); the null-space vector z follows the
        reference's joint acceleration plus a joint-limit-avoiding term.
        """
        ddx_d = self.arm.ee_jacobian(q_ref) @ ddq_ref + self.arm.ee_drift_acceleration(
            q_ref, dq_ref
        )
        z = ddq_ref + joint_limit_avoidance(self.robot, state.q, self.settings.null_space_gain)
        ddq_d = self.arm.resolved_acceleration(state.q, state.dq, ddx_d, z)
        return self.arm.inverse_dynamics(state.q, state.dq, ddq_d)

    def _reset_episode_state(self) -> None:
        self.intent = None
        self.planned = []
        self.subgoal = None
        self.radius_m = 0.0
        self.awaiting_trigger = False
        self.last_step_s = None
        self.hold_reason = None
        self.index = 0
