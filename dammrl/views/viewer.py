"""``dammrl view``: the stack live in Foxglove (its WebSocket protocol, foxglove-sdk).

The arm in 3D from its URDF (served to the app as an asset, posed by ``/tf`` transforms
from every RobotState), the goal and its button, the active subgoal with its admission
sphere and the fingertip's trail (``/dammrl/scene``), the human's commands and the model
in force (``/dammrl/decision``), error and pressure for plots. Every channel is JSON with
a JSON Schema (Foxglove's own for transforms and scenes), times are ``{sec, nsec}``, and
each topic is throttled so a viewer keeps up. A recording plays through the same
translator, so it looks the same as the live stack.
"""

from __future__ import annotations

import collections
import json
import threading
import time
import xml.etree.ElementTree as ElementTree
from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from foxglove.websocket import ChannelView, Client, ServerListener

from dammrl.views.wsgate import SubprotocolGate
from dammrl_core.robot import RobotDescription
from schemas import (
    DecodeError,
    EpisodeResult,
    Intent,
    Message,
    ModelChoice,
    RobotState,
    SensorSample,
    StepEvent,
    TaskGoal,
    decode,
    type_of,
)

WORLD = "world"
URDF_URL = "package://dammrl/robot.urdf"
"""Where the layout's URDF layer fetches the arm (the server answers with the URDF)."""
TRAIL_POINTS = 300
DEFAULT_MAX_HZ = 30.0

TIME = {"type": "object", "title": "time", "properties": {
    "sec": {"type": "integer", "minimum": 0},
    "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}  # fmt: skip


def stamp(t_ns: int) -> dict[str, int]:
    """Foxglove's time: whole seconds and nanoseconds (exact in JavaScript, unlike ns)."""
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def _object(title: str, **properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object",
            "properties": {"timestamp": TIME, **properties}}  # fmt: skip


NUMBER, INTEGER = {"type": "number"}, {"type": "integer"}
OPTIONAL_NUMBER, OPTIONAL_INTEGER = {"type": ["number", "null"]}, {"type": ["integer", "null"]}
VECTOR = {"type": "array", "items": NUMBER, "minItems": 3, "maxItems": 3}
OPTIONAL_VECTOR = {"type": ["array", "null"], "items": NUMBER, "minItems": 3, "maxItems": 3}
PLOT_SCHEMAS = {
    "/dammrl/error": _object("dammrl.Error", episode=INTEGER, error_m=NUMBER,
                             error_xyz_m=VECTOR, to_subgoal_m=OPTIONAL_NUMBER,
                             radius_m=OPTIONAL_NUMBER),
    "/dammrl/pressure": _object("dammrl.Pressure", raw=INTEGER, level=OPTIONAL_NUMBER,
                                pressed={"type": ["boolean", "null"]}),
    "/dammrl/decision": _object("dammrl.Decision", episode=INTEGER, u_h=INTEGER,
                                human_model=INTEGER, robot_model=OPTIONAL_INTEGER,
                                radius_m=NUMBER, steps_m=OPTIONAL_VECTOR,
                                correct={"type": ["boolean", "null"]}, p_small=OPTIONAL_NUMBER,
                                source={"type": "string"}),
    "/dammrl/episode": _object("dammrl.Episode", episode=INTEGER,
                               outcome={"type": "string"}, t_total_s=NUMBER),
}  # fmt: skip


def foxglove_schema(name: str) -> dict[str, Any]:
    """Foxglove's JSON Schema of one of its message types (from @foxglove/schemas 2.1)."""
    text = resources.files("dammrl.views.foxglove_schemas").joinpath(f"{name}.json").read_text()
    schema: dict[str, Any] = json.loads(text)
    return schema


class ArmFrames:
    """The URDF's link tree and its transforms for a joint vector (pinocchio FK)."""

    def __init__(self, robot: RobotDescription) -> None:
        import pinocchio as pin

        self.urdf = robot.urdf_path.read_text()
        self.model = robot.pinocchio_model()
        self.data = self.model.createData()
        root = ElementTree.fromstring(self.urdf)
        self.edges = [_link_pair(joint) for joint in root.iter("joint")]
        self.base = next(p for p, _ in self.edges if all(p != c for _, c in self.edges))
        self._frame = {name: self.model.getFrameId(name) for edge in self.edges for name in edge}
        self._pin = pin

    def transforms(self, q: np.ndarray, t_ns: int) -> dict[str, Any]:
        """FrameTransforms: world -> base, then parent -> child for every URDF joint."""
        pin = self._pin
        pin.forwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        pin.updateFramePlacements(self.model, self.data)
        world = {name: self.data.oMf[index] for name, index in self._frame.items()}
        rows = [_transform(WORLD, self.base, world[self.base], t_ns)]
        rows += [_transform(p, c, world[p].actInv(world[c]), t_ns) for p, c in self.edges]
        return {"transforms": rows}


def _link_pair(joint: ElementTree.Element) -> tuple[str, str]:
    """(parent link, child link) of a URDF joint."""
    parent, child = joint.find("parent"), joint.find("child")
    if parent is None or child is None:
        raise ValueError(f"URDF joint {joint.get('name')!r} lacks its parent or child link")
    return str(parent.get("link")), str(child.get("link"))


def _transform(parent: str, child: str, placement: Any, t_ns: int) -> dict[str, Any]:
    import pinocchio as pin

    x, y, z, w = pin.Quaternion(placement.rotation).coeffs()  # pinocchio: (x, y, z, w)
    tx, ty, tz = placement.translation
    return {"timestamp": stamp(t_ns), "parent_frame_id": parent, "child_frame_id": child,
            "translation": {"x": tx, "y": ty, "z": tz},
            "rotation": {"x": x, "y": y, "z": z, "w": w}}  # fmt: skip


class Throttle:
    """At most ``max_hz`` messages per topic, by message time (a replay throttles alike)."""

    def __init__(self, max_hz: float) -> None:
        self.period_ns = int(1e9 / max_hz)
        self.last: dict[str, int] = {}

    def allow(self, topic: str, t_ns: int) -> bool:
        last = self.last.get(topic)
        if last is not None and 0 <= t_ns - last < self.period_ns:
            return False
        self.last[topic] = t_ns
        return True


Log = Callable[[str, dict[str, Any], int], None]  # (topic, message, log time [ns])


class SceneTranslator:
    """Bus messages in, Foxglove messages out (through ``log``)."""

    def __init__(self, robot: RobotDescription, log: Log, max_hz: float = DEFAULT_MAX_HZ,
                 cap_radius_m: float = 0.03) -> None:  # fmt: skip
        self.arm = ArmFrames(robot)
        self.log, self.throttle = log, Throttle(max_hz)
        self.cap_radius_m = cap_radius_m
        self.goal: np.ndarray | None = None
        self.episode = 0
        self.step: StepEvent | None = None
        self.choice: ModelChoice | None = None
        self.trail: collections.deque[tuple[float, float, float]] = collections.deque(
            maxlen=TRAIL_POINTS
        )

    def feed(self, message: Message, t_ns: int) -> None:
        if isinstance(message, RobotState):
            self._state(message, t_ns)
        elif isinstance(message, TaskGoal):
            self.goal, self.episode, self.step = np.array(message.goal_m), message.episode, None
            self.trail.clear()
        elif isinstance(message, StepEvent):
            self.step = message
        elif isinstance(message, ModelChoice):
            self.choice = message
        elif isinstance(message, Intent):
            self._decision(message, t_ns)
        elif isinstance(message, SensorSample) and self.throttle.allow("pressure", t_ns):
            self.log("/dammrl/pressure", {"timestamp": stamp(t_ns), "raw": message.raw,
                     "level": message.level, "pressed": message.pressed}, t_ns)  # fmt: skip
        elif isinstance(message, EpisodeResult):
            self.log("/dammrl/episode", {"timestamp": stamp(t_ns), "episode": message.episode,
                     "outcome": "success" if message.success else message.outcome,
                     "t_total_s": message.t_total_s}, t_ns)  # fmt: skip

    def _state(self, state: RobotState, t_ns: int) -> None:
        self.trail.append(tuple(state.ee_pos_m))  # type: ignore[arg-type]
        if not self.throttle.allow("state", t_ns):
            return
        self.log("/tf", self.arm.transforms(np.array(state.q_rad), t_ns), t_ns)
        self.log("/dammrl/scene", self._scene(t_ns), t_ns)
        if self.goal is not None and state.episode == self.episode:
            error = np.array(state.ee_pos_m) - self.goal
            step = self.step
            to_subgoal = (float(np.linalg.norm(np.array(state.ee_pos_m) - step.subgoal_m))
                          if step is not None else None)  # fmt: skip
            self.log("/dammrl/error", {"timestamp": stamp(t_ns), "episode": state.episode,
                     "error_m": float(np.linalg.norm(error)), "error_xyz_m": error.tolist(),
                     "to_subgoal_m": to_subgoal,
                     "radius_m": step.radius_m if step is not None else None}, t_ns)  # fmt: skip

    def _decision(self, intent: Intent, t_ns: int) -> None:
        choice = self.choice
        posterior = choice.posterior if choice is not None else None
        self.log("/dammrl/decision", {
            "timestamp": stamp(t_ns), "episode": intent.episode, "u_h": intent.u_h,
            "human_model": intent.human_model, "radius_m": intent.radius_m,
            "robot_model": choice.robot_model if choice is not None else None,
            "steps_m": list(choice.steps_m) if choice is not None else None,
            "correct": intent.correct, "source": intent.source,
            "p_small": posterior[1] if posterior else None}, t_ns)  # fmt: skip

    def _scene(self, t_ns: int) -> dict[str, Any]:
        """Goal and button, the subgoal with its admission sphere, the trail."""
        entities = []
        if self.goal is not None:
            button = {"pose": _pose(self.goal - [0, 0, 0.005]), "bottom_scale": 1, "top_scale": 1,
                      "size": {"x": 2 * self.cap_radius_m, "y": 2 * self.cap_radius_m, "z": 0.01},
                      "color": _color(0.85, 0.1, 0.1, 1)}  # fmt: skip
            marker = _sphere(_point(self.goal), 0.008, (0.1, 0.8, 0.2, 1))
            entities.append(_entity("goal", t_ns, spheres=[marker], cylinders=[button]))
        if self.step is not None:
            centre = np.array(self.step.subgoal_m)
            entities.append(_entity("subgoal", t_ns, spheres=[
                _sphere(_point(centre), 2 * self.step.radius_m, (0.1, 0.5, 1.0, 0.35)),
                _sphere(_point(centre), 0.003, (0.1, 0.5, 1.0, 1.0))]))  # fmt: skip
        if len(self.trail) >= 2:
            points = [{"x": x, "y": y, "z": z} for x, y, z in self.trail]
            entities.append(_entity("trail", t_ns, lines=[{
                "type": 0, "pose": _pose(np.zeros(3)), "thickness": 2, "scale_invariant": True,
                "points": points, "color": _color(1.0, 0.55, 0.0, 1), "colors": [],
                "indices": []}]))  # fmt: skip
        return {"deletions": [], "entities": entities}


def _point(p: np.ndarray) -> dict[str, float]:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


def _pose(p: np.ndarray) -> dict[str, Any]:
    return {"position": _point(np.asarray(p, dtype=float)),
            "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}}  # fmt: skip


def _color(r: float, g: float, b: float, a: float) -> dict[str, float]:
    return {"r": r, "g": g, "b": b, "a": a}


def _sphere(centre: dict[str, float], diameter: float, rgba: tuple[float, ...]) -> dict[str, Any]:
    size = {"x": diameter, "y": diameter, "z": diameter}
    pose = {"position": centre, "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}}
    return {"pose": pose, "size": size, "color": _color(*rgba)}


def _entity(name: str, t_ns: int, **primitives: list[dict[str, Any]]) -> dict[str, Any]:
    entity: dict[str, Any] = {
        "timestamp": stamp(t_ns), "frame_id": WORLD, "id": name,
        "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "metadata": [],
    }  # fmt: skip
    for kind in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts",
                 "models"):  # fmt: skip
        entity[kind] = primitives.get(kind, [])
    return entity


class Subscribers(ServerListener):
    """Which channels a viewer has subscribed (the SDK's ServerListener): a recording waits
    for its first viewer instead of playing to no one."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._open: set[tuple[int, str]] = set()
        self.any = threading.Event()

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self._lock:
            self._open.add((client.id, channel.topic))
            self.any.set()

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        with self._lock:
            self._open.discard((client.id, channel.topic))
            if not self._open:
                self.any.clear()


class FoxgloveServer:
    """The WebSocket server and one JSON channel per topic; ``log`` is a translator's."""

    def __init__(self, robot: RobotDescription, host: str, port: int) -> None:
        import foxglove

        self._urdf = robot.urdf_path.read_bytes()
        self.clients = Subscribers()
        self.channels = {
            "/tf": foxglove.Channel("/tf", schema=self._schema("FrameTransforms"),
                                    message_encoding="json"),
            "/dammrl/scene": foxglove.Channel("/dammrl/scene", schema=self._schema("SceneUpdate"),
                                              message_encoding="json"),
            **{topic: foxglove.Channel(topic, schema=schema)
               for topic, schema in PLOT_SCHEMAS.items()},
        }  # fmt: skip
        # the SDK's server on a private loopback port; the public one is the gate's, which
        # also admits clients that name the protocol as ws-protocol does (Lichtblick)
        self.server = foxglove.start_server(name="dammrl", host="127.0.0.1", port=0,
                                            asset_handler=self._asset,
                                            server_listener=self.clients)  # fmt: skip
        self.gate = SubprotocolGate(host, port, int(self.server.port))

    @staticmethod
    def _schema(name: str) -> Any:
        import foxglove

        return foxglove.Schema(name=f"foxglove.{name}", encoding="jsonschema",
                               data=json.dumps(foxglove_schema(name)).encode())  # fmt: skip

    def _asset(self, uri: str) -> bytes | None:
        return self._urdf if uri == URDF_URL else None

    @property
    def port(self) -> int:
        return self.gate.port

    def log(self, topic: str, message: dict[str, Any], t_ns: int) -> None:
        self.channels[topic].log(message, log_time=t_ns)

    def stop(self) -> None:
        self.gate.stop()
        self.server.stop()


def bus_messages(
    settings: Any, stop: threading.Event, say: Callable[[str], None] | None = None
) -> Iterator[tuple[Message, int]]:
    """Every message of the stack on the bus, decoded, with its arrival time [ns]; ``say``
    hears within seconds if no stack let the session in."""
    from services.common.bus import tool_session

    with tool_session(settings, say) as session:
        subscriber = session.declare_subscriber(f"{settings.namespace}/**")
        while not stop.is_set():
            sample = subscriber.try_recv()
            if sample is None:
                time.sleep(0.002)
                continue
            message_type = type_of(settings.namespace, str(sample.key_expr))
            if message_type is None:
                continue
            try:
                yield decode(message_type, sample.payload.to_bytes()), time.time_ns()
            except DecodeError:
                continue  # a bad message is the recorder's and the services' business


def recording_messages(path: Path, rate: float, stop: threading.Event
                       ) -> Iterator[tuple[Message, int]]:  # fmt: skip
    """A recording's messages with their log times, paced at ``rate`` x real time (0: as
    fast as possible)."""
    from dammrl.stack.recording import read_recording

    started, first = time.monotonic(), None
    for log_time, message in read_recording(path).decoded(
        RobotState, TaskGoal, StepEvent, ModelChoice, Intent, SensorSample, EpisodeResult
    ):
        if stop.is_set():
            return
        first = log_time if first is None else first
        if rate > 0:
            delay = (log_time - first) * 1e-9 / rate - (time.monotonic() - started)
            if delay > 0:
                stop.wait(delay)
        yield message, log_time


def layout() -> str:
    """The Foxglove layout of ``dammrl view`` (JSON): the 3D arm beside the plots of the
    goal error and the pressure, and the decisions; built with foxglove-sdk's layouts."""
    import foxglove.layouts as fl

    arm = fl.ThreeDeePanel(title="arm", config=fl.ThreeDeeConfig(
        follow_tf=WORLD,
        layers={"urdf": fl.BaseRendererUrdfLayerSettings(
            layer_id="foxglove.Urdf", instance_id="urdf", label="rehab arm",
            source_type="url", url=URDF_URL, display_mode="auto", visible=True)},
        topics={"/dammrl/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True)},
    ))  # fmt: skip
    error = fl.PlotPanel(title="goal error [m]", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value="/dammrl/error.error_m"),
        fl.PlotSeries(value="/dammrl/error.to_subgoal_m"),
        fl.PlotSeries(value="/dammrl/error.radius_m")], show_legend=True))  # fmt: skip
    pressure = fl.PlotPanel(title="pressure (normalised)", config=fl.PlotConfig(
        paths=[fl.PlotSeries(value="/dammrl/pressure.level")], show_legend=True))  # fmt: skip
    decisions = fl.RawMessagesPanel(
        title="decisions and the model in force",
        config=fl.RawMessagesConfig(topic_path="/dammrl/decision"),
    )
    side = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=1, content=error), fl.SplitItem(proportion=1, content=pressure),
        fl.SplitItem(proportion=1, content=decisions)])  # fmt: skip
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=arm), fl.SplitItem(proportion=2, content=side)])
    ).to_json()  # fmt: skip
