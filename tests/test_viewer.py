"""``dammrl view``: a client speaking Foxglove's WebSocket protocol sees the channels, their
JSON Schemas and messages, and the arm's transform chain agrees with the kinematics."""

from __future__ import annotations

import json
import struct
import time
from collections import defaultdict
from typing import Any

import jsonschema
import numpy as np
import pytest

from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotDescription
from schemas import Header, RobotState, StepEvent, TaskGoal
from tests.busutil import free_port

foxglove = pytest.importorskip("foxglove")
websockets_client = pytest.importorskip("websockets.sync.client")

from dammrl.views.viewer import URDF_URL, FoxgloveServer, SceneTranslator, stamp  # noqa: E402

GOAL = (0.45, 0.02, -0.216)
RATE_HZ = 100.0


def _header(seq: int) -> Header:
    return Header(stamp_ns=time.time_ns(), seq=seq, source="test")


def _state(arm: ArmModel, seq: int, q: np.ndarray) -> RobotState:
    return RobotState(header=_header(seq), episode=1, t_s=seq / RATE_HZ, q_rad=tuple(q),
                      dq_rad_s=(0.0,) * 6, tau_nm=(0.0,) * 6,
                      ee_pos_m=tuple(arm.ee_position(q)), ee_vel_m_s=(0.0,) * 3,
                      button_pressed=False, button_travel_m=0.0, holding=False)  # fmt: skip


def _receive(ws: Any, until: float) -> tuple[list[dict[str, Any]], list[bytes]]:
    texts, binaries = [], []
    while time.monotonic() < until:
        try:
            frame = ws.recv(timeout=0.2)
        except TimeoutError:
            continue
        if isinstance(frame, str):
            texts.append(json.loads(frame))
        else:
            binaries.append(frame)
    return texts, binaries


def _compose(transforms: list[dict[str, Any]], frame: str) -> np.ndarray:
    """The position of ``frame``'s origin in the world, walking the chain up."""
    by_child = {t["child_frame_id"]: t for t in transforms}
    point = np.zeros(3)
    while frame in by_child:
        t = by_child[frame]
        r, p = t["rotation"], t["translation"]
        x, y, z, w = r["x"], r["y"], r["z"], r["w"]
        rotation = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])  # fmt: skip
        point = rotation @ point + np.array([p["x"], p["y"], p["z"]])
        frame = t["parent_frame_id"]
    assert frame == "world"
    return point


@pytest.mark.parametrize("subprotocol", ["foxglove.sdk.v1", "foxglove.websocket.v1"])
def test_a_foxglove_client_sees_the_arm_the_goal_and_the_plots(
    robot: RobotDescription, arm: ArmModel, subprotocol: str
) -> None:
    """The SDK's protocol name and ws-protocol's (Lichtblick's) reach the same server."""
    server = FoxgloveServer(robot, "127.0.0.1", free_port())
    translator = SceneTranslator(robot, server.log, max_hz=30)
    with websockets_client.connect(f"ws://127.0.0.1:{server.port}",
                                   subprotocols=[subprotocol]) as ws:  # fmt: skip
        assert ws.subprotocol == subprotocol
        texts, _ = _receive(ws, time.monotonic() + 1.0)
        advertised = {c["topic"]: c for t in texts if t["op"] == "advertise" for c in t["channels"]}
        assert {"/tf", "/dammrl/scene", "/dammrl/error", "/dammrl/decision"} <= set(advertised)
        assert all(c["encoding"] == "json" and c["schemaEncoding"] == "jsonschema"
                   for c in advertised.values())  # fmt: skip
        assert advertised["/tf"]["schemaName"] == "foxglove.FrameTransforms"
        wanted = [{"id": k, "channelId": c["id"]} for k, c in enumerate(advertised.values())]
        ws.send(json.dumps({"op": "subscribe", "subscriptions": wanted}))
        time.sleep(0.3)
        rng = np.random.default_rng(0)
        q_seen = {}
        t0 = 1_700_000_000 * 10**9
        translator.feed(TaskGoal(header=_header(0), episode=1, seed=7, start_m=(0.3, 0.0, -0.1),
                                 goal_m=GOAL, q_start_rad=(0.0,) * 6), t0)  # fmt: skip
        for seq in range(1, 101):  # 1 s of states at 100 Hz
            q = np.array([0.0, 1.0, 0.0, 1.6, 0.0, 0.3]) + rng.uniform(-0.3, 0.3, 6)
            t_ns = t0 + int(seq * 1e9 / RATE_HZ)
            q_seen[t_ns] = q
            translator.feed(_state(arm, seq, q), t_ns)
            if seq == 50:
                translator.feed(StepEvent(
                    header=_header(seq), episode=1, index=1, t_s=0.5, start_s=0.5,
                    trigger="event", u_h=1, radius_m=0.004, steps_m=(0.01,) * 3,
                    dx_m=(0.01, 0, 0), x_start_m=(0.3, 0, -0.1), subgoal_m=(0.31, 0, -0.1),
                    goal_error_m=0.2, ik_compute_s=0.01, ik_latency_s=0.01), t_ns)  # fmt: skip
        _, binaries = _receive(ws, time.monotonic() + 1.5)
    server.stop()

    topic_of = {k: c["topic"] for k, c in enumerate(advertised.values())}
    received: dict[str, list[tuple[int, dict[str, Any]]]] = defaultdict(list)
    for frame in binaries:
        assert frame[0] == 0x01  # MessageData
        subscription, log_time = struct.unpack_from("<IQ", frame, 1)
        received[topic_of[subscription]].append((log_time, json.loads(frame[13:])))
    for topic, messages in received.items():
        schema = json.loads(advertised[topic]["schema"])
        for _, message in messages:
            jsonschema.validate(message, schema)  # every message fits its advertised schema
    # throttled: 100 states in 1 s -> at most 30 per topic (and not none)
    assert 20 <= len(received["/tf"]) <= 31, len(received["/tf"])
    for log_time, message in received["/tf"]:
        tip = _compose(message["transforms"], robot.ee_frame)
        np.testing.assert_allclose(tip, arm.ee_position(q_seen[log_time]), atol=1e-9)
        assert message["transforms"][0]["timestamp"] == stamp(log_time)
    errors = [m for _, m in received["/dammrl/error"]]
    assert errors and all(m["timestamp"]["nsec"] < 10**9 for m in errors)
    scenes = [m for _, m in received["/dammrl/scene"]]
    last = {e["id"]: e for e in scenes[-1]["entities"]}
    assert {"goal", "subgoal", "trail"} <= set(last)
    assert last["subgoal"]["spheres"][0]["size"]["x"] == pytest.approx(0.008)  # 2 x radius
    assert server._asset(URDF_URL) == robot.urdf_path.read_bytes()
    assert server._asset("package://other/file") is None


def test_the_shipped_layout_is_the_generated_one() -> None:
    from pathlib import Path

    from dammrl.views.viewer import layout

    shipped = Path(__file__).resolve().parent.parent / "docs/foxglove_layout.json"
    assert json.loads(shipped.read_text()) == json.loads(layout())
    assert URDF_URL in shipped.read_text()
