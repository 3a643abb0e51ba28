"""The participant display: a page in any browser of the lab's network (viser serves it
and its web client from the wheel, no build step) showing what the participant needs to
decide, and nothing else.

- The arm, drawn from the URDF's collision geometry (cylinders, boxes, spheres) posed by
  each robot state with pinocchio's forward kinematics; the table; the goal button.
- The current subgoal with its admission sphere (its radius the chosen ε).
- A large, high-contrast cue: "Decide now: forward or back", with the input to use,
  while a decision request is open; when it is answered, or closes unanswered (the
  reach ended), it says so; a movement begun before the question, or with none open,
  is said to count for nothing; the outcome after each reach; the instructions before
  a block; the rest between blocks with its countdown.
- A comfort rating (1-5) after a block, returned to the caller (a session publishes it
  on the bus and logs it).

Operator tools (Foxglove through ``dammrl view``) stay apart: this page is for a patient,
possibly older, at arm's length from a screen: few things, large type, strong colours.
"""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import viser

from dammrl_core.robot import RobotDescription
from dammrl_core.task import TaskSettings
from schemas import (
    DecisionRequest,
    EpisodeResult,
    Intent,
    IntentEvidence,
    Message,
    RobotState,
    SessionControl,
    StepEvent,
    TaskGoal,
)

ARM = (205, 210, 220)
TABLE = (120, 92, 64)
GOAL = (230, 40, 40)
SUBGOAL = (40, 140, 255)
BACKGROUND_TEXT = "#ffffff"
CUE_COLOURS = {"decide": "#ffd000", "info": "#ffffff", "good": "#35e06a", "bad": "#ff6b5b"}
CAP_RADIUS_M = 0.03
COMFORT_SCALE = ((5, "very comfortable"), (4, "comfortable"), (3, "neither"),
                 (2, "uncomfortable"), (1, "very uncomfortable"))  # fmt: skip
BUTTON_STYLE = "button { min-height: 64px !important; font-size: 26px !important; }"
STATE_HZ = 30.0
"""The page is redrawn at most this often from the robot state (a screen shows 60 Hz)."""


@dataclass(frozen=True)
class Shape:
    """One collision shape of a link: its kind, size and placement on its joint."""

    kind: str  # cylinder, box or sphere
    size: tuple[float, ...]  # radius, length | x, y, z | radius [m]
    joint: int
    placement: Any  # pinocchio SE3 of the shape in its joint's frame


class ArmShapes:
    """The URDF's collision shapes and their world poses for a joint vector."""

    def __init__(self, robot: RobotDescription) -> None:
        import pinocchio as pin

        self._pin = pin
        self.model = robot.pinocchio_model()
        self.data = self.model.createData()
        geometry = pin.buildGeomFromUrdf(self.model, str(robot.urdf_path), pin.COLLISION)
        self.shapes = [s for s in map(_shape, geometry.geometryObjects) if s is not None]

    def poses(self, q: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """(position, quaternion w x y z) of every shape at ``q``."""
        pin = self._pin
        pin.forwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        poses = []
        for shape in self.shapes:
            world = self.data.oMi[shape.joint] * shape.placement
            x, y, z, w = pin.Quaternion(world.rotation).coeffs()
            poses.append((np.array(world.translation), np.array([w, x, y, z])))
        return poses


def _shape(geometry: Any) -> Shape | None:
    """A collision object as a Shape (None: a kind the display does not draw)."""
    kind = type(geometry.geometry).__name__
    g = geometry.geometry
    if kind == "Cylinder":
        size: tuple[float, ...] = (float(g.radius), 2 * float(g.halfLength))
    elif kind == "Box":
        size = tuple(2 * float(v) for v in g.halfSide)
    elif kind == "Sphere":
        size = (float(g.radius),)
    else:
        return None
    return Shape(kind.lower(), size, int(geometry.parentJoint), geometry.placement)


class ParticipantDisplay:
    """The page (see the module docstring); ``feed`` it bus messages from any thread."""

    def __init__(self, robot: RobotDescription, task: TaskSettings, host: str = "0.0.0.0",
                 port: int = 8080, decide_with: str = "Forward or back?") -> None:  # fmt: skip
        # a browser's dropped pre-connection is no error of ours
        logging.getLogger("websockets.server").setLevel(logging.CRITICAL)
        with contextlib.redirect_stdout(io.StringIO()):  # its banner: stdout is for results
            self.server = viser.ViserServer(host=host, port=port, label="dammrl", verbose=False)
        self.port = self.server.get_port()
        self.decide_with = decide_with
        self.arm = ArmShapes(robot)
        self._lock = threading.Lock()
        self._drawn_s = 0.0
        self.frames = 0  # robot states drawn
        self.episode = 0
        self.guided = False  # the therapist has taken the decisions over
        self.asking: tuple[int, int] | None = None  # the open request (episode, number)
        self._scene(task)
        self._panel()
        self.say("Welcome", "The session starts soon.")

    # ---- the scene ----------------------------------------------------------------
    def _scene(self, task: TaskSettings) -> None:
        server = self.server
        server.gui.configure_theme(control_width="large", dark_mode=True, show_logo=False,
                                   show_share_button=False)  # fmt: skip
        server.gui.main_panel.dock_right()
        server.scene.set_up_direction("+z")
        # where a seated participant beside the arm looks from: over the shoulder
        server.initial_camera.position = (0.0, -0.8, 0.3)
        server.initial_camera.look_at = (0.3, 0.0, -0.2)
        top = task.table_top_z_m
        server.scene.add_box("/table", TABLE, (0.9, 1.0, 0.04),
                             position=(0.35, 0.0, top - 0.02))  # fmt: skip
        self.goal = server.scene.add_cylinder("/goal", CAP_RADIUS_M, 0.012, GOAL,
                                              position=(0.4, 0.0, top), visible=False)  # fmt: skip
        # a halo over the true-size cap: a 6 cm button is small on a screen
        self.halo = server.scene.add_icosphere("/goal/halo", 0.05, GOAL, opacity=0.3)
        self.subgoal = server.scene.add_icosphere("/subgoal", 0.01, SUBGOAL, opacity=0.55,
                                                  visible=False)  # fmt: skip
        self.subgoal_centre = server.scene.add_icosphere("/subgoal_centre", 0.004, SUBGOAL,
                                                         visible=False)  # fmt: skip
        self.links = [self._add_shape(i, s) for i, s in enumerate(self.arm.shapes)]
        self.show_state(np.zeros(len(self.arm.model.names) - 1))

    def _add_shape(self, index: int, shape: Shape) -> Any:
        name, scene = f"/arm/{index}", self.server.scene
        if shape.kind == "cylinder":
            return scene.add_cylinder(name, shape.size[0], shape.size[1], ARM)
        if shape.kind == "box":
            return scene.add_box(name, ARM, np.array(shape.size))
        return scene.add_icosphere(name, shape.size[0], (255, 170, 40))

    def show_state(self, q: np.ndarray) -> None:
        with self.server.atomic():
            for handle, (position, wxyz) in zip(self.links, self.arm.poses(q), strict=True):
                handle.position, handle.wxyz = position, wxyz
        self.frames += 1

    # ---- the words ----------------------------------------------------------------
    def _panel(self) -> None:
        # large touch targets: the panel's buttons at the height of a finger
        self.server.gui.add_html(f"<style>{BUTTON_STYLE}</style>")
        self.text = self.server.gui.add_html("")
        self._rated: list[int] = []  # the rating given since the question was shown
        self._answered = threading.Event()
        self.comfort = [self._rating_button(n, label) for n, label in COMFORT_SCALE]

    def _rating_button(self, rating: int, label: str) -> Any:
        button = self.server.gui.add_button(f"{rating}   {label}", visible=False)
        button.on_click(lambda _: self._take_rating(rating))
        return button

    def _take_rating(self, rating: int) -> None:
        if self.comfort[0].visible and not self._answered.is_set():
            self._rated.append(rating)
            self._answered.set()

    def say(self, title: str, line: str = "", tone: str = "info") -> None:
        """A title and a line in large type, coloured by ``tone`` (info, decide, good, bad)."""
        colour = CUE_COLOURS[tone]
        self.text.content = (
            f'<div style="padding:12px;font-family:sans-serif;color:{BACKGROUND_TEXT}">'
            f'<div style="font-size:44px;font-weight:700;color:{colour};line-height:1.1">'
            f"{_escape(title)}</div>"
            f'<div style="font-size:26px;margin-top:14px;line-height:1.3">{_escape(line)}</div>'
            "</div>"
        )

    def rest(self, seconds: float, stop: threading.Event | None = None) -> None:
        """A rest screen counting down ``seconds`` (until ``stop`` is set)."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0 and not (stop and stop.is_set()):
            self.say("Rest", f"Relax your arm. We go on in {left:.0f} s.")
            time.sleep(min(1.0, left))

    def ask_comfort(self, timeout_s: float) -> tuple[int, float] | None:
        """Show the rating until the participant answers or ``timeout_s`` passes; (rating,
        seconds it took) or None."""
        self._rated.clear()
        self._answered.clear()
        self.say("How comfortable was that block?", "Touch one answer.", "decide")
        for button in self.comfort:
            button.visible = True
        asked = time.monotonic()
        self._answered.wait(timeout_s)
        for button in self.comfort:
            button.visible = False
        choice = list(self._rated)
        if not choice:
            return None
        self.say("Thank you", "", "good")
        return choice[0], time.monotonic() - asked

    # ---- the bus ------------------------------------------------------------------
    def feed(self, message: Message) -> None:
        """One bus message (states redrawn at most STATE_HZ)."""
        with self._lock:
            if isinstance(message, RobotState):
                now = time.monotonic()
                if now - self._drawn_s >= 1.0 / STATE_HZ:
                    self._drawn_s = now
                    self.show_state(np.array(message.q_rad))
            elif isinstance(message, TaskGoal):
                self._new_reach(message)
            elif isinstance(message, StepEvent):
                self.subgoal.position = self.subgoal_centre.position = message.subgoal_m
                self.subgoal.scale = message.radius_m / 0.01  # the sphere's radius is 1 cm
                self.subgoal.visible = self.subgoal_centre.visible = True
            elif isinstance(message, SessionControl):
                self._control(message)
            elif isinstance(message, DecisionRequest):
                self._ask(message)
            elif isinstance(message, Intent):
                self._show_answer(message)
            elif isinstance(message, IntentEvidence):
                self._not_counted(message)
            elif isinstance(message, EpisodeResult):
                self._outcome(message)

    def _ask(self, request: DecisionRequest) -> None:
        if (request.episode, request.request) == self.asking:
            return  # sent again: the same question
        self.asking = (request.episode, request.request)
        if self.guided:
            self.say("Your therapist decides", "Relax and watch the arm.")
        else:
            self.say("Decide now", self.decide_with, "decide")

    def _show_answer(self, intent: Intent) -> None:
        if (intent.episode, intent.request) != self.asking:
            return  # a repeat of an earlier answer
        self.asking = None
        way = "forward" if intent.u_h > 0 else "back"
        who = "Your therapist chose" if not intent.person and self.guided else "You chose"
        self.say("Answered: moving", f"{who} {way}.")

    def _not_counted(self, evidence: IntentEvidence) -> None:
        """A movement that answers no question: the person is told why."""
        if evidence.acted or self.guided:
            return
        if "before the request opened" in evidence.reason:
            self.say("Too early", "That movement began before the question. Relax, then "
                     "answer.", "bad")  # fmt: skip
        elif evidence.reason == "no request open":
            self.say("No question now", "That movement counts for nothing. Wait for "
                     "'Decide now'.", "bad")  # fmt: skip

    def _control(self, control: SessionControl) -> None:
        if control.action == "take":
            self.guided = True
            self.say("Your therapist decides", "Relax and watch the arm.")
        elif control.action == "give":
            self.guided = False
            self.say("Your turn again", self.decide_with)
        elif control.action == "pause":
            self.say("Paused", "Relax. We go on soon.")
        elif control.action == "resume":
            self.say("Going on", "")

    def _new_reach(self, goal: TaskGoal) -> None:
        if goal.episode == self.episode:
            return  # announced again
        self.episode = goal.episode
        x, y, z = goal.goal_m
        self.goal.position = (x, y, z - 0.006)  # the cap's top at the goal point
        self.goal.wxyz = (1.0, 0.0, 0.0, 0.0)
        self.goal.visible = True
        self.subgoal.visible = self.subgoal_centre.visible = False
        self.asking = None  # an earlier reach's question closed with it
        self.say("Get ready", "Reach for the red button.")

    def _outcome(self, result: EpisodeResult) -> None:
        closed = " The question is closed: no need to answer it." if self.asking else ""
        self.asking = None
        if result.success:
            self.say("Well done!", f"Button pressed in {result.t_total_s:.0f} s.{closed}", "good")
        else:
            self.say("Reach ended", f"That one did not reach the button.{closed} Next one "
                     "soon.", "bad")  # fmt: skip

    def close(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


Feed = Callable[[Message], None]


DISPLAYED = (RobotState, TaskGoal, StepEvent, DecisionRequest, Intent, IntentEvidence,
             EpisodeResult, SessionControl)  # fmt: skip


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
