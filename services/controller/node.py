"""The controller node: the reach supervisor (``Reach``) and its controller on the bus.

Each RobotState of the running episode is one ``Reach.tick``: its JointCommand (and
StepEvents) go out; when the reach asks for a decision, a DecisionRequest goes out, the
policy answers it with a ModelChoice and the human with an Intent, which becomes due at
the request time plus the human's decision time on the robot clock (a late answer is due
on arrival). Without RobotState for ``state_stale_s`` the episode ends in a hold (the
sim holds the arm by itself once commands stop).

A tick's command goes out first: before its decision request, and before the IK of a
step planned from a resting reference (whose tick's command the plan cannot change,
``Controller.tick``). In lockstep (``DAMMRL_BUS_LOCKSTEP``) the command answering a state
that asked for a decision waits for the human's answer, so the robot clock never runs
past a due time before the answer is known: the stack then reproduces the in-process
runner exactly.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Sequence

from dammrl_core import state as core
from dammrl_core.control.pause import Pause, hold_command
from dammrl_core.control.reach import Plan, Reach, plan_reach
from dammrl_core.control.settings import ControllerSettings, check_workspace
from dammrl_core.dynamics import ArmModel
from dammrl_core.ik import make_ik_solver
from dammrl_core.metrics import episode_summary
from dammrl_core.models import ModelSet
from dammrl_core.robot import RobotSettings
from dammrl_core.safety import StopLatch
from dammrl_core.task import TaskSettings
from schemas import (
    ENDS_REACH,
    DecisionRequest,
    EmergencyStop,
    EpisodeResult,
    GoalRefused,
    Intent,
    JointCommand,
    Message,
    ModelChoice,
    RobotState,
    SessionControl,
    StepEvent,
    TaskGoal,
    decode,
    encode,
)
from services.common import convert
from services.common.bus import Bus
from services.common.entry import run_service
from services.common.runtime import cpu_wait_s
from services.common.security import OPERATOR
from services.controller.requests import Requests, Timing

log = logging.getLogger("dammrl.controller")
MAX_STATE_STEP_S = 0.5  # robot time between two states (10 ms at 100 Hz) can be no more
ANNOUNCE_PERIOD_S = 0.5  # TaskGoal is repeated until the sim answers with the new episode


class ControllerNode:
    def __init__(
        self,
        settings: ControllerSettings,
        task: TaskSettings,
        robot: RobotSettings,
        models: ModelSet,
        bus: Bus,
    ) -> None:
        check_workspace(settings, task)
        self.settings = settings
        self.task_settings = task
        self.models = models
        self.bus = bus
        self.robot = robot.load()
        self.arm = ArmModel(self.robot)
        self.ik = make_ik_solver(
            settings.ik_solver, self.arm, settings.joint_limit_margin_rad,
            settings.max_joint_step_rad,
        )  # fmt: skip
        self.control_dt_s = 1.0 / settings.control_rate_hz
        # in lockstep the robot clock waits for us: only a dead sim leaves the state stale
        lockstep = bus.settings.lockstep
        self.stale_s = bus.settings.lockstep_timeout_s if lockstep else settings.state_stale_s
        # in lockstep the answer must come within the wait for it: ask again sooner
        resend = settings.request_resend_s
        self.timing = Timing(
            min(resend, bus.settings.lockstep_timeout_s / 8) if lockstep else resend,
            bus.settings.lockstep_timeout_s / 4 if lockstep else settings.choice_wait_s,
        )
        self.choice = (settings.human_model, settings.robot_model)  # until the policy speaks
        self.plan: Plan | None = None
        self.number = 0  # the running episode's number (0: none yet)
        self.requests = Requests(0, 0, models, self.timing)
        self.started = False  # the arm has answered the episode's TaskGoal
        self.previous_command: core.JointCommand | None = None  # the last reach's, till reset
        self.announced_s = 0.0
        self.last_state_s = time.monotonic()
        self.loop_s = time.monotonic()  # when the loop last ran
        self.loop_cpu_wait_s = cpu_wait_s()  # this thread's wait for a CPU by then
        self.superseded = 0  # states observed, not answered: a newer one was waiting
        self.last_t = 0.0
        self.last_state_stamp_ns: int | None = None  # of the last state the reach took in
        self.commands = bus.publisher(JointCommand)
        self.steps = bus.publisher(StepEvent)
        self.asks = bus.publisher(DecisionRequest)
        self.goals = bus.publisher(TaskGoal)
        self.results = bus.publisher(EpisodeResult)
        bus.subscribe(RobotState, Intent, ModelChoice, SessionControl, EmergencyStop, GoalRefused)
        bus.expect(RobotState, "sim", "robot")  # the simulated or the real arm
        bus.expect(GoalRefused, "sim", "robot")
        bus.expect(Intent, "intent")
        bus.expect(ModelChoice, "policy")
        bus.expect(SessionControl, OPERATOR)  # the session's console
        bus.expect(EmergencyStop, OPERATOR)  # `dammrl stop`, the console's x
        self.pause = Pause()  # the therapist's pauses of the running reach
        self.last_command: core.JointCommand | None = None  # the last command sent
        self.answered = False  # the state being ticked has had its command
        self.stop_latch = StopLatch()  # no reach runs, and no goal goes out, while stopped
        self.next_due_s: float | None = None  # when the next reach may begin (its outcome held)
        # who paused the session between two reaches (the next waits): a session holds the
        # first until it is attached (its stop one key away)
        self.held_next = settings.first_reach_held_by

    @property
    def reach(self) -> Reach | None:
        return None if self.plan is None else self.plan.reach

    def run(self, stop: threading.Event) -> None:
        self._wait_for_peers(stop)
        self.next_due_s = time.monotonic()  # the first reach: at once, unless stopped
        while not stop.is_set():
            self._dispatch_all(self.bus.receive_all(0.02))
            self._watch()
            holding = (
                self.pause.paused
                or self.stop_latch.engaged
                or bool(self.held_next)
                or (self.reach is not None and self.reach.controller.hold_reason is not None)
            )
            self.bus.report_health("holding" if holding else "ok", self._waiting_for())

    def _stalled_itself(self, now: float) -> bool:
        """Whether this process stopped running for longer than the state's staleness since
        the last look (frozen, swapped out, starved): the arm held meanwhile for lack of
        commands, and the episode ends in a hold that names the controller, not the arm."""
        silent, self.loop_s = now - self.loop_s, now
        waited, self.loop_cpu_wait_s = self.loop_cpu_wait_s, cpu_wait_s()
        if silent <= self.stale_s or self.reach is None or not self.started:
            return False
        reason = f"the controller itself stalled for {silent:.2f} s (the arm held)"
        if waited is not None and self.loop_cpu_wait_s is not None:
            reason += f"; {self.loop_cpu_wait_s - waited:.2f} s of it waiting for a CPU"
        log.warning("%s", reason)
        self.reach.end("hold", reason, self.last_t)
        self._finish()
        return True

    def _waiting_for(self) -> str:
        """What the controller waits for, and since when; states it had to skip (Health
        detail)."""
        late = f"{self.superseded} states superseded before answered"
        if self.stop_latch.reason is not None:
            return f"{self.stop_latch.reason}: the next reach waits for its release; {late}"
        if self.held_next:
            return f"paused by {self.held_next} before reach {self.number + 1}; {late}"
        if self.pause.paused:
            return f"paused by the session's console; {late}"
        if self.reach is not None and self.reach.asked:
            since = time.monotonic() - self.requests.sent_s
            number = self.requests.number
            return f"waiting for the answer to request {number} ({since:.1f} s); {late}"
        return late

    def _wait_for_peers(self, stop: threading.Event) -> None:
        """Start the first episode once the policy speaks (its first ModelChoice), so every
        decision is the policy's, and the human service is alive, so it hears the episode's
        announcement; after ``policy_wait_s`` go on (the configured model; requests are
        sent again until a human answers). A policy that came alive gets ``policy_wait_s``
        from then: a busy machine's start-up (every service importing at once) is not
        counted against it, and the first reach does not start into that start-up."""
        wait_s = self.settings.policy_wait_s
        deadline = time.monotonic() + wait_s
        spoke = policy_seen = False
        while not stop.is_set() and time.monotonic() < deadline:
            message = self.bus.receive(0.1)
            if isinstance(message, ModelChoice):
                self.choice = (message.human_model, message.robot_model)
                spoke = True
            elif isinstance(message, EmergencyStop):
                self._take_stop(message)
            elif isinstance(message, SessionControl):
                self._take_control(message)  # the session's resume of the first reach
            alive = self.bus.alive_peers()
            if not policy_seen and "policy" in alive:
                policy_seen = True
                deadline = max(deadline, time.monotonic() + wait_s)
            human = "intent" in alive
            if spoke and human:
                return
            waiting = " and ".join(
                w for w, ok in (("the policy", spoke), ("intent", human)) if not ok
            )
            self.bus.report_health("holding", f"waiting for {waiting}")
        if not spoke:
            log.warning("no ModelChoice from the policy: starting with M_%d,%d", *self.choice)
        if "intent" not in self.bus.alive_peers():
            log.warning("no intent service alive: starting; requests repeat until one answers")

    # ---- messages -----------------------------------------------------------------
    def _dispatch_all(self, messages: list[Message]) -> None:
        """The answers (intent, model choice) first: they carry their own due times; then
        the states, of which only the newest is answered (a command planned from an
        older state would reach the arm late and be clamped by its caps): the others are
        observed (logged, judged), not answered."""
        states = [m for m in messages if isinstance(m, RobotState)]
        for message in messages:
            if not isinstance(message, RobotState):
                self._dispatch_other(message)
        for state in states[:-1]:
            self._on_state(state, answer=False)
        if states:
            self._on_state(states[-1])

    def _dispatch_other(self, message: Message) -> None:
        if isinstance(message, Intent | ModelChoice):
            self._take_answer(message)
        elif isinstance(message, SessionControl):
            self._take_control(message)
        elif isinstance(message, EmergencyStop):
            self._take_stop(message)
        elif isinstance(message, GoalRefused):
            self._take_refusal(message)

    def _take_refusal(self, refusal: GoalRefused) -> None:
        """The arm cannot begin the announced episode: it ends as a hold that says why (the
        console shows it), and the next one follows. A refusal of any other episode (one
        begun, ended, or not yet announced) is stale: ignored."""
        if self.plan is None or self.started or refusal.episode != self.number:
            return
        arm = refusal.header.source
        log.warning("episode %d refused by the %s: %s", self.number, arm, refusal.reason)
        self.plan.reach.end("hold", f"the {arm} cannot begin it: {refusal.reason}", 0.0)
        self._finish()

    def _take_answer(self, message: Intent | ModelChoice) -> None:
        asked = self.reach is not None and self.reach.asked
        if isinstance(message, Intent):
            self.requests.take_intent(message, asked)
        else:
            self.requests.take_choice(message)
        self._answer_if_complete()

    def _on_state(self, message: RobotState, answer: bool = True) -> None:
        taken_s, plan = time.monotonic(), self.plan
        if message.episode != self.number:
            if answer and not self.started and message.episode == self.number - 1:
                self._hold_until_reset(message)
            return
        if plan is None:  # between reaches, or after the last: it holds where it was left
            if answer and not self.stop_latch.engaged:
                self._hold_paused(message.header.stamp_ns)
            return
        if (reason := self._implausible_time(message.t_s)) is not None:
            self.bus.reject(self.bus.key(RobotState), reason)
            return
        state = convert.robot_state(message)
        self.last_t = state.t_s
        self.last_state_stamp_ns = message.header.stamp_ns  # the reach's result names it
        # the reach runs on its own clock, stopped while paused
        state = dataclasses.replace(state, t_s=self.pause.reach_time(state.t_s))
        if not self.started:
            self.started = True
            log.info("episode %d started (seed %d)", self.number, plan.seed)
        if not answer:
            self.superseded += 1
            if not self.pause.paused and plan.reach.observe(state) is not None:
                self._finish()
            return
        if self.pause.paused:
            self._hold_paused(message.header.stamp_ns)
            return
        stamp, self.answered = message.header.stamp_ns, False
        # the arm's command first, before a step's IK (``early``) and the decision request,
        # except in lockstep, where it waits for the answer (the robot clock must not pass
        # the answer's due time)
        tick = plan.reach.tick(state, early=lambda command: self._send_command(command, stamp))
        lockstep = self.bus.settings.lockstep
        if not (tick.ask and lockstep):
            self._send_command(tick.command, stamp)
        if tick.ask:
            self.asks.send(self.requests.make(self.asks.stamp, state.t_s, state.ee_pos,
                                              plan.task.goal, self.settings.primary_axis,
                                              self.choice[0]))  # fmt: skip
            if lockstep:
                self._await_answer()
                if self.plan is not plan:
                    return  # a stop ended the reach while it waited
                self._send_command(tick.command, stamp)
        for step in tick.steps:
            self.steps.send(convert.step_message(self.steps.stamp(), step, self.number))
        self.last_state_s = time.monotonic()
        if tick.ended is not None:
            self._finish()
        elif not lockstep:  # in lockstep the next state comes at once
            self.bus.rehearse(taken_s + self.control_dt_s, lambda: self._rehearse(message))

    def _rehearse(self, message: RobotState) -> None:
        """The next state's answer rehearsed on this one (``Bus.rehearse``): decoded (from
        its encoding: the payload was the bus's), converted, the controller's quiet tick,
        a command built and encoded; nothing sent or kept."""
        reach, command = self.reach, self.last_command
        if reach is None or command is None:
            return
        reach.controller.rehearse(convert.robot_state(decode(RobotState, encode(message))))
        encode(convert.command_message(message.header, command, self.number,
                                       message.header.stamp_ns))  # fmt: skip

    def _send_command(self, command: core.JointCommand | None, state_stamp_ns: int) -> None:
        """The tick's command to the arm, answering the state stamped ``state_stamp_ns``
        (once: a command sent early is not sent again)."""
        if command is not None and not self.answered:
            self.answered = True
            self.last_command = command
            self.commands.send(convert.command_message(
                self.commands.stamp(), command, self.number, state_stamp_ns
            ))  # fmt: skip

    def _hold_until_reset(self, message: RobotState) -> None:
        """The next reach is announced, the arm not yet reset: it holds the last reach's
        final reference, answered state by state (else it holds for want of commands, and
        says so, every time between two reaches)."""
        if not self.stop_latch.engaged:
            self._send_hold(self.previous_command, message.episode, message.header.stamp_ns)

    def _hold_paused(self, state_stamp_ns: int) -> None:
        """Paused (or between two reaches): the arm holds the last reference at rest."""
        self.last_state_s = time.monotonic()
        self._send_hold(self.last_command, self.number, state_stamp_ns)

    def _send_hold(self, last: core.JointCommand | None, episode: int, state_stamp_ns: int) -> None:
        """``last``'s reference held at rest, answering a state of ``episode`` (None: no
        reference yet, nothing sent: the arm holds where it is, as it does unasked)."""
        if last is None:
            return
        hold = hold_command(self.arm, last, self.robot.tau_max)
        self.commands.send(convert.command_message(
            self.commands.stamp(), hold, episode, state_stamp_ns
        ))  # fmt: skip

    def _take_stop(self, stop: EmergencyStop) -> None:
        """An emergency stop ends the running reach at once (outcome ``stopped``: the arm
        may be moved by hand meanwhile, so the reach never goes on from its plan) and holds
        back the next reach's goal until the release."""
        if not self.stop_latch.take(stop.engaged, stop.header.source, stop.reason):
            return
        if self.stop_latch.engaged:  # the arm may be moved by hand: no old reference after
            self.last_command = self.previous_command = None  # the release (it holds where it is)
        reach = self.reach
        if self.stop_latch.reason is None:
            log.warning("emergency stop released by %s", stop.header.source)
        elif reach is not None and reach.ended is None:
            log.warning("%s: reach %d ended", self.stop_latch.reason, self.number)
            reach.end("stopped", self.stop_latch.reason, self.pause.reach_time(self.last_t))
            self._finish()

    def _take_control(self, control: SessionControl) -> None:
        """The therapist's pause, resume or skip of the running reach (another episode's
        is late: ignored); a pause between two reaches holds the next one back."""
        reach = self.reach
        if reach is None and control.episode == self.number + 1:
            self._hold_next(control)
            return
        if reach is None or control.episode != self.number or reach.ended is not None:
            log.info("%s of episode %d ignored: not running", control.action, control.episode)
            return
        who = f"{control.who}" + (f": {control.why}" if control.why else "")
        if control.action == "pause" and self.pause.begin(self.last_t):
            log.warning("paused by %s", who)
        elif control.action == "resume" and self.pause.end(self.last_t):
            log.warning("resumed by %s (paused %.1f s in all)", who, self.pause.total_s)
        elif control.action in ENDS_REACH:
            self.pause.end(self.last_t)
            reach.end("skipped", f"skipped by {who}", self.pause.reach_time(self.last_t))
            self._finish()

    def _hold_next(self, control: SessionControl) -> None:
        """A pause or resume between two reaches: the next reach waits for the resume."""
        if control.action == "pause" and not self.held_next:
            self.held_next = control.who + (f": {control.why}" if control.why else "")
            log.warning("paused by %s before reach %d", self.held_next, self.number + 1)
        elif control.action == "resume" and self.held_next:
            self.held_next = ""
            log.warning("resumed by %s before reach %d", control.who, self.number + 1)

    def _implausible_time(self, t_s: float) -> str | None:
        """Why a state's robot time cannot follow the last one (a forged or stray state).
        The first state may come at any time: a restarted controller takes over a reach."""
        if self.started and not self.last_t < t_s <= self.last_t + MAX_STATE_STEP_S:
            return f"robot time {t_s:.3f} s after {self.last_t:.3f} s (backwards or a jump)"
        return None

    def _resend_if_unanswered(self) -> None:
        """Never a silent wait: the same request again while nobody answered it (not
        while paused: nobody is asked to decide then)."""
        asked = self.reach is not None and self.reach.asked and not self.pause.paused
        if (again := self.requests.again(self.asks.stamp, asked)) is not None:
            self.asks.send(again)

    def _await_answer(self) -> None:
        """Lockstep: take messages until the human answered the open request (bounded)."""
        deadline = time.monotonic() + self.bus.settings.lockstep_timeout_s / 2
        while self.reach is not None and self.reach.asked:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                log.warning("lockstep: no answer to request %d in time", self.requests.number)
                return
            message = self.bus.receive(min(remaining, 0.01))
            if isinstance(message, Intent | ModelChoice):
                self._take_answer(message)
            elif isinstance(message, EmergencyStop):
                self._take_stop(message)  # it may end the reach: the loop ends with it
            self._answer_if_complete()
            self._resend_if_unanswered()

    def _answer_if_complete(self) -> None:
        """Hand the human's answer to the reach with the step vector the policy chose for
        the same request (see ``Requests.answer``)."""
        reach = self.reach
        if reach is None or (done := self.requests.answer()) is None:
            return
        answer, chosen = done
        if chosen is not None:
            self.choice = chosen
        reach.answer(answer)

    # ---- episodes -----------------------------------------------------------------
    def _watch(self) -> None:
        """Begin the next reach once its predecessor's outcome was held (not while stopped
        or paused); announce the running episode until it starts; end it when the state
        is stale."""
        now = time.monotonic()
        if self._stalled_itself(now):
            return
        due = self.next_due_s is not None and now >= self.next_due_s
        if due and not self.stop_latch.engaged and not self.held_next:
            self.next_due_s = None
            self._next_episode()
        self._answer_if_complete()
        self._resend_if_unanswered()
        if (
            self.plan is not None
            and not self.started
            and now - self.announced_s > ANNOUNCE_PERIOD_S
        ):
            self._announce(self.plan)
        stale = now - self.last_state_s > self.stale_s
        if self.reach is not None and self.started and stale:
            self.reach.end("hold", self._why_no_state(), self.last_t)
            self._finish()

    def _why_no_state(self) -> str:
        """Who went silent: the arm's service (alive but silent, or gone)."""
        alive = self.bus.alive_peers()
        arm = next((a for a in ("robot", "sim") if a in alive), None)
        silent = f"for {self.stale_s:.2f} s"
        if arm is None:
            return f"robot state stale: no arm service alive (sim or robot gone) {silent}"
        return f"robot state stale: {arm} alive but silent {silent}"

    def _next_episode(self) -> None:
        number = self.number + 1
        total = self.task_settings.episodes
        if total is not None and number > total:
            self.plan = None
            log.info("all %d episodes done", total)
            return
        seed = self.task_settings.seed + number - 1
        self.number = number
        self.plan = plan_reach(seed, self.settings, self.task_settings, self.robot, self.arm,
                               self.ik, self.control_dt_s)  # fmt: skip
        self.requests = Requests(number, seed, self.models, self.timing)
        self.started = False
        self.previous_command = self.last_command
        self.pause, self.last_command = Pause(), None
        self.last_state_stamp_ns = None
        self._announce(self.plan)
        # planning is this process working, before the arm moves: the stall clock starts
        # here (a plan slower than the state's staleness ended the first reach at once)
        self.loop_s = time.monotonic()

    def _announce(self, plan: Plan) -> None:
        self.announced_s = time.monotonic()
        self.goals.send(TaskGoal(
            header=self.goals.stamp(),
            episode=self.number,
            seed=plan.seed,
            start_m=tuple(float(v) for v in plan.task.start),
            goal_m=tuple(float(v) for v in plan.task.goal),
            q_start_rad=tuple(float(v) for v in plan.q_start),
        ))  # fmt: skip

    def _finish(self) -> None:
        plan = self.plan
        assert plan is not None
        metrics = plan.reach.metrics()
        summary = episode_summary(metrics, self.settings.trigger, self.choice, plan.seed, plan.task)
        self.results.send(convert.episode_result(self.results.stamp(), self.number, summary,
                                                 self.last_state_stamp_ns))  # fmt: skip
        log.info(
            "episode %d: %s (%s) in %.1f s",
            self.number, metrics.outcome, metrics.reason, metrics.t_total_s,
        )  # fmt: skip
        self.plan = None  # the next reach begins in _watch, once the outcome was held
        self.next_due_s = time.monotonic() + self.settings.outcome_hold_s


def main(argv: Sequence[str] | None = None) -> int:
    """Controller service: micro-steps, trigger, IK, joint commands, episodes."""
    return run_service(
        "controller",
        "Controller service: micro-steps, trigger, IK, joint commands, episodes.",
        "DAMMRL_CONTROLLER_*, DAMMRL_TASK_*, DAMMRL_ROBOT_*, DAMMRL_MODELS_*",
        lambda bus, _: ControllerNode(
            ControllerSettings(), TaskSettings(), RobotSettings(), ModelSet(), bus
        ),
        argv,
    )
