"""The controller node: the controller core and the episode supervisor on the bus.

Loop: take the next message; a RobotState of the running episode ticks the core and
sends the JointCommand (plus StepEvents and, when the core wants a decision, one
DecisionRequest); an Intent answering the open request goes to the core; a ModelChoice
sets the step vector. Without RobotState for ``state_stale_s`` the core holds its last
reference and the episode ends (the sim holds the arm by itself once commands stop).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence

import numpy as np

from dammrl.robot import RobotDescription
from dammrl.robot.scene import SceneLayout
from dammrl.task import TaskSettings, seed_streams
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
from services.controller.dynamics import ArmModel
from services.controller.ik import DampedLeastSquaresIK
from services.controller.supervisor import Episode, Supervisor
from services.intent.config import HumanSettings
from services.sim.config import SimSettings

log = logging.getLogger("dammrl.controller")
ANNOUNCE_PERIOD_S = 0.5  # TaskGoal is repeated until the sim answers with the new episode


class ControllerNode:
    def __init__(
        self,
        settings: ControllerSettings,
        task: TaskSettings,
        sim: SimSettings,
        bus: Bus,
    ) -> None:
        self.settings = settings
        self.task_settings = task
        self.bus = bus
        robot = RobotDescription.from_urdf(sim.urdf_path, sim.ee_frame, sim.armature_kgm2)
        arm = ArmModel(robot)
        layout = SceneLayout(table_top_z_m=sim.table_top_z_m)
        self.supervisor = Supervisor(task, DampedLeastSquaresIK(arm), layout.goal_z_m)
        self.controller = Controller(robot, settings, np.random.default_rng(task.seed), arm)
        models = HumanSettings().models
        self.choice = (settings.human_model, settings.robot_model)
        self.controller.set_steps(models.steps_m(settings.robot_model))
        self.episode: Episode | None = None
        self.started = False  # the sim has answered the episode's TaskGoal
        self.announced_s = 0.0
        self.last_state_s = time.monotonic()
        self.last_t = 0.0
        self.request = 0
        self.request_open = False
        self.publish = {
            t: bus.publisher(t)
            for t in (JointCommand, StepEvent, DecisionRequest, TaskGoal, EpisodeResult)
        }
        bus.subscribe(RobotState, Intent, ModelChoice)
        bus.expect(RobotState, "sim")
        bus.expect(Intent, "intent")
        bus.expect(ModelChoice, "policy")

    def run(self, stop: threading.Event) -> None:
        self._wait_for_policy(stop)
        self._next_episode()
        while not stop.is_set():
            message = self.bus.receive(0.02)
            if message is not None:
                self._dispatch(message)
            self._watch()
            self.bus.report_health("holding" if self.controller.hold_reason else "ok")

    def _wait_for_policy(self, stop: threading.Event) -> None:
        """Start the first episode once the policy speaks (its first ModelChoice), so every
        decision is the policy's; after ``policy_wait_s`` go on with the configured model."""
        deadline = time.monotonic() + self.settings.policy_wait_s
        while not stop.is_set() and time.monotonic() < deadline:
            message = self.bus.receive(0.1)
            if isinstance(message, ModelChoice):
                self._dispatch(message)
                return
            self.bus.report_health("holding", "waiting for the policy")
        log.warning("no ModelChoice from the policy: starting with M_%d,%d", *self.choice)

    # ---- messages -----------------------------------------------------------------
    def _dispatch(self, message: Message) -> None:
        if isinstance(message, RobotState):
            self._on_state(message)
        elif isinstance(message, Intent):
            self._on_intent(message)
        elif isinstance(message, ModelChoice):
            self._on_choice(message)

    def _on_choice(self, message: ModelChoice) -> None:
        """The policy's answer to the open request, or its periodic repeat between steps."""
        answers_open = message.request == self.request and self.request_open
        if message.request >= 0 and not answers_open:
            return  # an answer to an older request
        self.choice = (message.human_model, message.robot_model)
        self.controller.set_steps(np.array(message.steps_m))

    def _on_state(self, message: RobotState) -> None:
        episode = self.episode
        if episode is None or message.episode != episode.number:
            return
        self.last_state_s = time.monotonic()
        state = convert.robot_state(message)
        self.last_t = state.t_s
        if not self.started:
            self.started = True
            self.controller.reset(state, episode.task.goal)
            self.controller.latency.rng = seed_streams(episode.seed)[2]
            log.info("episode %d started (seed %d)", episode.number, episode.seed)
        episode.record(state)
        if (ended := self.supervisor.finished(episode, state)) is not None:
            self._finish(*ended)
            return
        output = self.controller.tick(state)
        self.publish[JointCommand].publish(
            **convert.command_fields(output.command, episode.number, message.header.stamp_ns)
        )
        for step in output.steps:
            episode.steps.append(step)
            self.publish[StepEvent].publish(**convert.step_fields(step, episode.number))
        if output.hold_reason is not None:
            self._finish("hold", output.hold_reason)
        elif self.controller.wants_intent and not self.request_open:
            self._request_decision(state.ee_pos, episode)

    def _request_decision(self, ee_pos: np.ndarray, episode: Episode) -> None:
        self.request += 1
        self.request_open = True
        self.publish[DecisionRequest].publish(
            episode=episode.number,
            request=self.request,
            t_s=self.last_t,
            ee_pos_m=tuple(float(v) for v in ee_pos),
            goal_m=tuple(float(v) for v in episode.task.goal),
            primary_axis=self.settings.primary_axis,
            human_model=self.choice[0],
        )

    def _on_intent(self, message: Intent) -> None:
        episode = self.episode
        if episode is None or message.episode != episode.number or message.request != self.request:
            return  # an answer to an older request
        self.request_open = False
        self.controller.on_intent(convert.intent(message, self.last_t))
        if message.correct is not None:
            episode.decisions.append(message.correct)

    # ---- episodes -----------------------------------------------------------------
    def _watch(self) -> None:
        """Announce the running episode until it starts; end it when the state is stale."""
        now = time.monotonic()
        if (
            self.episode is not None
            and not self.started
            and now - self.announced_s > ANNOUNCE_PERIOD_S
        ):
            self._announce(self.episode)
        stale = now - self.last_state_s > self.settings.state_stale_s
        if self.episode is not None and self.started and stale:
            self._finish("hold", f"robot state stale: none for {self.settings.state_stale_s:.2f} s")

    def _next_episode(self) -> None:
        number = 1 if self.episode is None else self.episode.number + 1
        total = self.task_settings.episodes
        if total is not None and number > total:
            self.episode = None
            log.info("all %d episodes done", total)
            return
        self.episode = self.supervisor.episode(number)
        self.started = False
        self.request_open = False
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

    def _finish(self, outcome: str, reason: str) -> None:
        episode = self.episode
        assert episode is not None
        self.controller.hold(reason, self.last_t)
        metrics = episode.metrics(outcome, reason)
        fields = metrics.as_dict()
        if fields["t_step_mean_s"] != fields["t_step_mean_s"]:  # NaN: no step taken
            fields["t_step_mean_s"] = None
        self.publish[EpisodeResult].publish(
            episode=episode.number,
            seed=episode.seed,
            trigger=self.settings.trigger,
            model=self.choice,
            start_m=tuple(float(v) for v in episode.task.start),
            goal_m=tuple(float(v) for v in episode.task.goal),
            **fields,
        )
        log.info(
            "episode %d: %s (%s) in %.1f s", episode.number, outcome, reason, metrics.t_total_s
        )
        self._next_episode()


def main(argv: Sequence[str] | None = None) -> int:
    """Controller service: micro-steps, trigger, IK, joint commands, episodes."""
    return run_service(
        "controller",
        "Controller service: micro-steps, trigger, IK, joint commands, episodes.",
        "DAMMRL_CONTROLLER_*, DAMMRL_TASK_*, DAMMRL_SIM_* (robot)",
        lambda bus, _: ControllerNode(ControllerSettings(), TaskSettings(), SimSettings(), bus),
        argv,
    )
