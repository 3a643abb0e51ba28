"""`dammrl view --recording` against the official `@foxglove/ws-protocol` npm client (the
protocol Lichtblick and older Foxglove releases speak): it connects, sees every channel,
parses every message, gets one transform tree rooted at `world` and the URDF asset; the
recording waits for it and plays again while it stays."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dammrl_core.dynamics import ArmModel
from schemas import TaskGoal, encode, key
from services.recorder.core import McapRecorder
from tests.busutil import Lines, free_port
from tests.test_viewer import GOAL, _header, _state

pytest.importorskip("foxglove")
JS = Path(__file__).parent / "js"
pytestmark = pytest.mark.skipif(shutil.which("node") is None, reason="needs node (Debian: nodejs)")


@pytest.fixture(scope="module")
def ws_protocol_client() -> Path:
    """The npm client, installed from the lock file on first use."""
    if not (JS / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        npm = shutil.which("npm")
        assert npm is not None, "npm is needed to install @foxglove/ws-protocol"
        subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=JS, check=True,
                       capture_output=True, timeout=300)  # fmt: skip
    return JS / "ws_protocol_client.mjs"


def _recording(path: Path, arm: ArmModel) -> Path:
    """Two seconds of a reach, as the recorder writes it."""
    recorder = McapRecorder(path, "dammrl", {"mode": "virtual"}, chunk_bytes=1 << 20)
    t0 = 1_700_000_000 * 10**9
    goal = TaskGoal(header=_header(0), episode=1, seed=7, start_m=(0.3, 0.0, -0.1),
                    goal_m=GOAL, q_start_rad=(0.0,) * 6)  # fmt: skip
    recorder.record(key("dammrl", TaskGoal, "sim"), encode(goal), t0)
    for seq in range(1, 201):
        q = np.array([0.0, 1.0, 0.0, 1.6, 0.0, 0.3]) + 0.1 * np.sin(seq / 20)
        state = _state(arm, seq, q)
        recorder.record(key("dammrl", type(state), "sim"), encode(state), t0 + seq * 10**7)
    recorder.finish()
    return path


def test_the_ws_protocol_client_connects_and_a_recording_waits_for_it_and_loops(
    ws_protocol_client: Path, arm: ArmModel, tmp_path: Path
) -> None:
    from dammrl_core.robot import RobotDescription

    recording = _recording(tmp_path / "reach.mcap", arm)
    port = free_port()
    view = subprocess.Popen(
        [sys.executable, "-m", "dammrl", "view", "--recording", str(recording), "--port",
         str(port)], stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert view.stderr is not None
        Lines(view.stderr).wait_for("waiting for a viewer", 60)
        time.sleep(3)  # nobody connected: nothing is played meanwhile
        assert view.poll() is None
        done = subprocess.run(["node", str(ws_protocol_client), f"ws://127.0.0.1:{port}", "6",
                               "package://dammrl/robot.urdf"],
                              capture_output=True, text=True, timeout=60)  # fmt: skip
        assert done.returncode == 0, done.stderr
        seen = json.loads(done.stdout)
    finally:
        view.terminate()
        view.wait(10)
    assert seen["subprotocol"] == "foxglove.websocket.v1" and not seen["errors"], seen["errors"]
    topics = {c["topic"]: c for c in seen["channels"]}
    assert {"/tf", "/dammrl/scene", "/dammrl/error", "/dammrl/decision"} <= set(topics)
    assert all(c["encoding"] == "json" and c["schemaEncoding"] == "jsonschema"
               for c in topics.values())  # fmt: skip
    assert seen["unparsable"] == 0
    # 2 s recorded, 6 s connected: played more than once (30 Hz cap -> ~60 per play)
    assert seen["messages"]["/tf"] > 70, seen["messages"]
    transforms = seen["lastTf"]["transforms"]
    parents = {t["parent_frame_id"] for t in transforms}
    children = {t["child_frame_id"] for t in transforms}
    assert parents - children == {"world"}  # one tree, rooted at the world
    urdf = RobotDescription.from_urdf().urdf_path.read_text()
    assert seen["asset"]["status"] == 0 and seen["asset"]["text"] == urdf
