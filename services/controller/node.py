"""The controller node: the reach supervisor (``Reach``) and its controller on the bus.

Each RobotState of the running episode is one ``Reach.tick``: its JointCommand (and
StepEvents) go out; when the reach asks for a decision, a DecisionRequest goes out, the
policy answers it with a ModelChoice and the human with an Intent, which becomes due at
the request time plus the human's decision time on the robot clock (a late answer is due
on arrival). Without RobotState for ``state_stale_s`` the episode ends in a hold (the
sim holds the arm by itself once commands stop).

In lockstep (``DAMMRL_BUS_LOCKSTEP``) the command answering a state that asked for a
decision waits for the human's answer, so the robot clock never runs past a due time
before the answer is known: the stack then reproduces the in-process runner exactly.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dammrl.core.dynamics import ArmModel
from dammrl.core.ik import make_ik_solver
from dammrl.core.metrics import episode_summary
from dammrl.core.models import ModelSet
from dammrl.core.robot import RobotSettings
from dammrl.core.state import Intent as CoreIntent
from dammrl.core.task import ReachTask, TaskSettings, seed_streams, start_posture, task_for_seed
from schemas import (
    DecisionRequest,
    EpisodeResult,
    Intent,
    JointCommand,
    Message,
    ModelChoice,
    RobotState,
    StepEvent,
    TaskGoal,
)
from services.common import convert
from services.common.bus import Bus
from services.common.entry import run_service
from services.controller.config import ControllerSettings
from services.controller.core import Controller
from services.controller.reach import Answer, Reach

log = logging.getLogger("dammrl.controller")
MAX_STATE_STEP_S = 0.5  # robot time between two states (10 ms at 100 Hz) can be no more
ANNOUNCE_PERIOD_S = 0.5  # TaskGoal is repeated until the sim answers with the new episode


@dataclass(frozen=True)
class Episode:
    number: int
    seed: int
    task: ReachTask
    q_start: np.ndarray


class ControllerNode:
    def __init__(
        self,
        settings: ControllerSettings,
        task: TaskSettings,
        robot: RobotSettings,
        models: ModelSet,
        bus: Bus,
    ) -> None:
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
        self.choice_wait_s = (
            bus.settings.lockstep_timeout_s / 4 if lockstep else settings.choice_wait_s
        )
        # in lockstep the answer must come within the wait for it: ask again sooner
        resend = settings.request_resend_s
        self.resend_s = min(resend, bus.settings.lockstep_timeout_s / 8) if lockstep else resend
        self.choice = (settings.human_model, settings.robot_model)  # until the policy speaks
        self.episode: Episode | None = None
        self.reach: Reach | None = None
        self.started = False  # the sim has answered the episode's TaskGoal
        self.announced_s = 0.0
        self.last_state_s = time.monotonic()
        self.loop_s = time.monotonic()  # when the loop last ran
        self.superseded = 0  # states observed, not answered: a newer one was waiting
        self.last_t = 0.0
        self.request = 0
        self.request_t_s = 0.0
        self.choices: dict[int, ModelChoice] = {}  # the policy's answer per request
        self.intent: Intent | None = None  # the human's answer, until matched with a choice
        self.request_fields: dict[str, Any] = {}  # the open request, to send it again
        self.request_sent_s = 0.0
        self.intent_wall_s = 0.0
        self.publish = {
            t: bus.publisher(t)
            for t in (JointCommand, StepEvent, DecisionRequest, TaskGoal, EpisodeResult)
        }
        bus.subscribe(RobotState, Intent, ModelChoice)
        bus.expect(RobotState, "sim", "robot")  # the simulated or the real arm
        bus.expect(Intent, "intent")
        bus.expect(ModelChoice, "policy")

    def run(self, stop: threading.Event) -> None:
        self._wait_for_peers(stop)
        self._next_episode()
        while not stop.is_set():
            self._dispatch_all(self.bus.receive_all(0.02))
            self._watch()
            holding = self.reach is not None and self.reach.controller.hold_reason is not None
            self.bus.report_health("holding" if holding else "ok", self._waiting_for())

    def _stalled_itself(self, now: float) -> bool:
        """Whether this process stopped running for longer than the state's staleness since
        the last look (frozen, swapped out, starved): the arm held meanwhile for lack of
        commands, and the episode ends in a hold that names the controller, not the arm."""
        silent, self.loop_s = now - self.loop_s, now
        if silent <= self.stale_s or self.reach is None or not self.started:
            return False
        reason = f"the controller itself stalled for {silent:.2f} s (the arm held)"
        log.warning("%s", reason)
        self.reach.end("hold", reason, self.last_t)
        self._finish()
        return True

    def _waiting_for(self) -> str:
        """What the controller waits for, and since when; states it had to skip (Health
        detail)."""
        late = f"{self.superseded} states superseded before answered"
        if self.reach is not None and self.reach.asked:
            since = time.monotonic() - self.request_sent_s
            return f"waiting for the answer to request {self.request} ({since:.1f} s); {late}"
        return late

    def _wait_for_peers(self, stop: threading.Event) -> None:
        """Start the first episode once the policy speaks (its first ModelChoice), so every
        decision is the policy's, and the human service is alive, so it hears the episode's
        announcement; after ``policy_wait_s`` go on (the configured model; requests are
        sent again until a human answers)."""
        deadline = time.monotonic() + self.settings.policy_wait_s
        spoke = False
        while not stop.is_set() and time.monotonic() < deadline:
            message = self.bus.receive(0.1)
            if isinstance(message, ModelChoice):
                self.choice = (message.human_model, message.robot_model)
                spoke = True
            human = "intent" in self.bus.alive_peers()
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
                self._dispatch(message)
        for state in states[:-1]:
            self._on_state(state, answer=False)
        if states:
            self._on_state(states[-1])

    def _dispatch(self, message: Message) -> None:
        if isinstance(message, RobotState):
            self._on_state(message)
        elif isinstance(message, Intent):
            self._on_intent(message)
        elif isinstance(message, ModelChoice):
            self._on_choice(message)

    def _on_choice(self, message: ModelChoice) -> None:
        """Keep the policy's answer to a request of this episode (periodic repeats only
        say the policy is alive); it may arrive before or after the human's."""
        episode = self.episode
        if episode is not None and message.episode == episode.number and message.request > 0:
            self.choices[message.request] = message
            self._answer_if_complete()

    def _on_state(self, message: RobotState, answer: bool = True) -> None:
        episode, reach = self.episode, self.reach
        if episode is None or reach is None or message.episode != episode.number:
            return
        if (reason := self._implausible_time(message.t_s)) is not None:
            self.bus.reject(self.bus.key(RobotState), reason)
            return
        state = convert.robot_state(message)
        self.last_t = state.t_s
        if not self.started:
            self.started = True
            log.info("episode %d started (seed %d)", episode.number, episode.seed)
        if not answer:
            self.superseded += 1
            if reach.observe(state) is not None:
                self._finish()
            return
        tick = reach.tick(state)
        if tick.ask:
            self._request_decision(state.ee_pos, episode)
            if self.bus.settings.lockstep:
                self._await_answer()
        if tick.command is not None:
            self.publish[JointCommand].publish(
                **convert.command_fields(tick.command, episode.number, message.header.stamp_ns)
            )
        for step in tick.steps:
            self.publish[StepEvent].publish(**convert.step_fields(step, episode.number))
        self.last_state_s = time.monotonic()
        if tick.ended is not None:
            self._finish()

    def _implausible_time(self, t_s: float) -> str | None:
        """Why a state's robot time cannot follow the last one (a forged or stray state).
        The first state may come at any time: a restarted controller takes over a reach."""
        if self.started and not self.last_t < t_s <= self.last_t + MAX_STATE_STEP_S:
            return f"robot time {t_s:.3f} s after {self.last_t:.3f} s (backwards or a jump)"
        return None

    def _request_decision(self, ee_pos: np.ndarray, episode: Episode) -> None:
        self.request += 1
        self.request_t_s = self.last_t
        self.request_fields = {
            "episode": episode.number,
            "seed": episode.seed,
            "request": self.request,
            "t_s": self.last_t,
            "ee_pos_m": tuple(float(v) for v in ee_pos),
            "goal_m": tuple(float(v) for v in episode.task.goal),
            "primary_axis": self.settings.primary_axis,
            "human_model": self.choice[0],
        }
        self._send_request()

    def _send_request(self) -> None:
        self.request_sent_s = time.monotonic()
        self.publish[DecisionRequest].publish(**self.request_fields)

    def _resend_if_unanswered(self) -> None:
        """Never a silent wait: the same request again while nobody answered it (a service
        that joined late or restarted; intent and policy answer a repeat with their first
        answer)."""
        waiting = self.reach is not None and self.reach.asked and self.intent is None
        if waiting and time.monotonic() - self.request_sent_s > self.resend_s:
            log.warning("request %d unanswered for %.1f s: sending it again",
                        self.request, time.monotonic() - self.request_sent_s)  # fmt: skip
            self._send_request()

    def _await_answer(self) -> None:
        """Lockstep: take messages until the human answered the open request (bounded)."""
        deadline = time.monotonic() + self.bus.settings.lockstep_timeout_s / 2
        while self.reach is not None and self.reach.asked:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                log.warning("lockstep: no answer to request %d in time", self.request)
                return
            message = self.bus.receive(min(remaining, 0.01))
            if isinstance(message, Intent | ModelChoice):
                self._dispatch(message)
            self._answer_if_complete()
            self._resend_if_unanswered()

    def _on_intent(self, message: Intent) -> None:
        episode, reach = self.episode, self.reach
        stale = message.request != self.request or reach is None or not reach.asked
        if episode is None or message.episode != episode.number or stale:
            return  # an answer to an older request
        self.intent, self.intent_wall_s = message, time.monotonic()
        self._answer_if_complete()

    def _answer_if_complete(self) -> None:
        """Hand the human's answer to the reach with the step vector the policy chose for
        the same request; without the policy's choice after ``choice_wait_s``, the steps
        in force stay (the human then decided under the request's own i)."""
        message, reach = self.intent, self.reach
        if message is None or reach is None:
            return
        choice = self.choices.get(message.request)
        waited = time.monotonic() - self.intent_wall_s > self.choice_wait_s
        if choice is None and not waited:
            return
        if choice is not None:
            self.choice = (choice.human_model, choice.robot_model)
        due_s = self.request_t_s + message.decision_s  # a late answer is due on arrival
        # radius and steps come from the stack's model set by index, never as free numbers
        # from a message (the schema alone would allow 0.1 m steps)
        radius_m = self.models.radius_m(message.human_model)
        intent = CoreIntent(due_s, message.u_h, radius_m, message.human_model, message.confidence)
        steps = None if choice is None else self.models.steps_m(choice.robot_model)
        reach.answer(Answer(intent, steps, message.correct))
        self.intent = None

    # ---- episodes -----------------------------------------------------------------
    def _watch(self) -> None:
        """Announce the running episode until it starts; end it when the state is stale."""
        now = time.monotonic()
        if self._stalled_itself(now):
            return
        self._answer_if_complete()
        self._resend_if_unanswered()
        if (
            self.episode is not None
            and not self.started
            and now - self.announced_s > ANNOUNCE_PERIOD_S
        ):
            self._announce(self.episode)
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
        number = 1 if self.episode is None else self.episode.number + 1
        total = self.task_settings.episodes
        if total is not None and number > total:
            self.episode = self.reach = None
            log.info("all %d episodes done", total)
            return
        seed = self.task_settings.seed + number - 1
        task = task_for_seed(self.task_settings, seed)
        q_start = start_posture(self.arm, self.task_settings, task.start)
        self.episode = Episode(number, seed, task, q_start)
        streams = seed_streams(seed)
        controller = Controller(self.robot, self.settings, streams.ik_latency, self.arm, self.ik)
        self.reach = Reach(controller, task, self.task_settings, self.control_dt_s)
        self.started = False
        self.request, self.choices, self.intent = 0, {}, None
        self._announce(self.episode)

    def _announce(self, episode: Episode) -> None:
        self.announced_s = time.monotonic()
        self.publish[TaskGoal].publish(
            episode=episode.number,
            seed=episode.seed,
            start_m=tuple(float(v) for v in episode.task.start),
            goal_m=tuple(float(v) for v in episode.task.goal),
            q_start_rad=tuple(float(v) for v in episode.q_start),
        )

    def _finish(self) -> None:
        episode, reach = self.episode, self.reach
        assert episode is not None and reach is not None
        metrics = reach.metrics()
        summary = episode_summary(
            metrics, self.settings.trigger, self.choice, episode.seed, episode.task
        )
        summary["reason"] = str(summary["reason"])[:500]  # the message's bound
        self.publish[EpisodeResult].publish(episode=episode.number, **summary)
        log.info(
            "episode %d: %s (%s) in %.1f s",
            episode.number, metrics.outcome, metrics.reason, metrics.t_total_s,
        )  # fmt: skip
        self._next_episode()


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
