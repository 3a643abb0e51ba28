"""The participant display: the screens (``screens``), the scene (``scene``) and the
page's server (``server``) put together, fed by the session's steps and the stack's bus."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from dammrl.people.display.scene import ArmShapes, stage
from dammrl.people.display.screens import END, INPUTS, Inputs, Place, Screen, Screens
from dammrl.people.display.server import VERSION, PageServer
from dammrl_core.robot import RobotDescription
from dammrl_core.task import TaskSettings
from schemas import (
    DecisionRequest,
    EmergencyStop,
    EpisodeResult,
    Intent,
    IntentEvidence,
    Message,
    RobotState,
    SessionControl,
    StepEvent,
    TaskGoal,
)

STATE_HZ = 30.0
"""The arm is redrawn at most this often from the robot state (a screen shows 60 Hz)."""
TONES = ("info", "decide", "good", "bad")


class ParticipantDisplay:
    """The page (see the package docstring); ``feed`` it bus messages from any thread."""

    def __init__(self, robot: RobotDescription, task: TaskSettings, host: str = "0.0.0.0",
                 port: int = 8080, inputs: Inputs = INPUTS["simulated"],
                 large_text: bool = False) -> None:  # fmt: skip
        self.arm = ArmShapes(robot)
        self.screens = Screens(inputs)
        self._lock = threading.Lock()
        self._drawn_s = 0.0
        self.frames = 0  # robot states drawn
        self._marks: dict[str, Any] = {"t": "marks", "goal": None, "subgoal": None}
        self._rating: tuple[int, int] | None = None  # (question, rating) once answered
        self._answered = threading.Event()
        self.server = PageServer(host, port, self._from_page)
        self.port = self.server.port
        shown = "localhost" if host in ("0.0.0.0", "127.0.0.1", "", "::") else host
        self.url = f"http://{shown}:{self.port}/"
        self.server.publish("hello", {"t": "hello", "version": VERSION, "large": large_text,
                                      "stage": stage(task)})  # fmt: skip
        self.server.publish("marks", self._marks)
        self._show()
        self.show_state(np.array(task.home_q_rad))

    def pages(self) -> int:
        """Participant pages connected now."""
        return self.server.connected()

    # ---- the session's steps ----------------------------------------------------------
    def say(self, title: str, line: str = "", tone: str = "info") -> None:
        """A title and a line in large type (tone: info, decide, good or bad)."""
        self._step(lambda s: s.show(Screen("info", title, line, tone if tone in TONES else "info")))

    def block(self, title: str, instructions: str) -> None:
        """A block's instructions, before it begins."""
        self._step(lambda s: s.show(Screen("block", title, instructions)))

    def expect_run(self, places: dict[int, Place], intent_source: str) -> None:
        """A new stack run: its reaches' places, who decides and with which input."""
        from dammrl.people.display.screens import inputs_for

        self._step(lambda s: s.expect_run(places, inputs_for(intent_source)))

    def rest(self, seconds: float) -> None:
        """The rest's screen, counting ``seconds`` down on the page's own clock."""
        self._step(lambda s: s.rest(seconds))

    def stopped(self) -> None:
        """The session's emergency stop (typed while no stack runs): the stop screen."""
        self._step(lambda s: s.stop(True))

    def released(self) -> None:
        self._step(lambda s: s.stop(False))

    def end(self) -> None:
        self._step(lambda s: s.show(END))

    def ask_comfort(self, timeout_s: float, cancel: threading.Event | None = None
                    ) -> tuple[int, float] | None:  # fmt: skip
        """Ask how comfortable the block was until the participant answers, ``timeout_s``
        passes or ``cancel`` is set; (rating 1-5, seconds it took) or None."""
        with self._lock:
            self._rating = None
            self._answered.clear()
            question = self.screens.comfort()
            self._show()
        asked = time.monotonic()
        while not self._answered.wait(0.1):
            if time.monotonic() - asked >= timeout_s or (cancel is not None and cancel.is_set()):
                break
        with self._lock:
            answer = self._rating
            rating = answer[1] if answer is not None and answer[0] == question else None
            self.screens.answered(rating)
            self._show()
        return None if rating is None else (rating, time.monotonic() - asked)

    def _from_page(self, message: dict[str, Any]) -> None:
        """A page's message: a comfort answer to the question on screen (any other, or a
        late one, changes nothing)."""
        question, value = message.get("question"), message.get("value")
        if message.get("t") != "rating" or type(value) is not int or not 1 <= value <= 5:
            return  # (true is an int to isinstance: never a rating)
        with self._lock:
            if question == self.screens.question and not self._answered.is_set():
                self._rating = (question, value)
                self._answered.set()

    # ---- the bus ------------------------------------------------------------------------
    def feed(self, message: Message) -> None:
        """One bus message (states redrawn at most STATE_HZ)."""
        if isinstance(message, RobotState):
            now = time.monotonic()
            with self._lock:
                if now - self._drawn_s < 1.0 / STATE_HZ:
                    return
                self._drawn_s = now
            self.show_state(np.array(message.q_rad))
            return
        with self._lock:
            if isinstance(message, TaskGoal) and message.episode != self.screens.episode:
                self._marks |= {"goal": list(message.goal_m), "subgoal": None}
                self.server.publish("marks", self._marks)
            elif isinstance(message, DecisionRequest) and message.episode > self.screens.episode:
                self._marks |= {"goal": list(message.goal_m), "subgoal": None}  # goal unheard
                self.server.publish("marks", self._marks)
            elif isinstance(message, StepEvent):
                self._marks |= {"subgoal": list(message.subgoal_m), "radius_m": message.radius_m}
                self.server.publish("marks", self._marks)
            if self.screens.take(message):
                self._show()

    def show_state(self, q: np.ndarray) -> None:
        self.server.publish("arm", {"t": "arm", "shapes": self.arm.drawn(q)})
        self.frames += 1

    def _step(self, change: Callable[[Screens], None]) -> None:
        with self._lock:
            change(self.screens)
            self._show()

    def _show(self) -> None:
        self.server.publish("screen", self.screens.screen.message(self.screens.inputs))

    def close(self) -> None:
        self.server.close()


DISPLAYED = (RobotState, TaskGoal, StepEvent, DecisionRequest, Intent, IntentEvidence,
             EpisodeResult, SessionControl, EmergencyStop)  # fmt: skip


class BusFeed:
    """Feeds a display from a stack's bus: subscribers on ``session`` that decode and hand
    on every message the display draws (bad messages are the services' business)."""

    def __init__(self, display: ParticipantDisplay, namespace: str) -> None:
        self.display, self.namespace = display, namespace
        self.subscribers: list[Any] = []  # kept: a dropped subscriber stops

    def attach(self, session: Any) -> None:
        """Subscribe on ``session`` (a stack's hub, while it runs)."""
        from schemas import DecodeError, decode, key

        for message_type in DISPLAYED:

            def take(sample: Any, message_type: type[Message] = message_type) -> None:
                try:
                    self.display.feed(decode(message_type, sample.payload.to_bytes()))
                except DecodeError:
                    return

            self.subscribers.append(
                session.declare_subscriber(key(self.namespace, message_type), take)
            )
