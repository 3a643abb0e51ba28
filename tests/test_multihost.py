"""Services on separate machines: Linux network namespaces as hosts on one bridge.

sim on host 1 (listening), controller + intent + policy on host 2, the recorder and a
watching tool on host 3, all with the lab's credentials (mutual TLS + ACL); an outsider on
host 4 without credentials can neither join nor read. Needs root and ``ip netns``; skips
with the reason otherwise. The namespaces and their processes are removed in teardown.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.common.certificates import create_credentials

pytestmark = pytest.mark.slow
SUBNET = "10.211.{tag}.{host}"  # addresses inside this test's own namespaces only
HOSTS = (1, 2, 3, 4)


def _can_make_namespaces() -> str | None:
    if sys.platform != "linux" or shutil.which("ip") is None:
        return "needs Linux with iproute2 (ip netns)"
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    probe = f"dmprobe{uuid.uuid4().hex[:6]}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, check=False)
    if made.returncode != 0:
        return f"cannot create network namespaces here: {made.stderr.decode().strip()}"
    subprocess.run(["ip", "netns", "del", probe], check=False)
    return None


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


class Lab:
    """Four namespaces ('hosts') joined by a bridge in a fifth ('switch')."""

    def __init__(self) -> None:
        self.tag = uuid.uuid4().hex[:5]
        self.net = int(self.tag, 16) % 200 + 20
        self.switch = f"dmsw{self.tag}"
        self.hosts = {h: f"dmh{h}{self.tag}" for h in HOSTS}
        self.processes: list[subprocess.Popen[bytes]] = []
        _ip("netns", "add", self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")
        for h, ns in self.hosts.items():
            _ip("netns", "add", ns)
            _ip("link", "add", f"v{h}{self.tag}", "netns", ns, "type", "veth",
                "peer", "name", f"p{h}", "netns", self.switch)  # fmt: skip
            _ip("-n", self.switch, "link", "set", f"p{h}", "master", "br0", "up")
            _ip("-n", ns, "link", "set", f"v{h}{self.tag}", "name", "eth0")
            _ip("-n", ns, "addr", "add", f"{self.address(h)}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")
            _ip("-n", ns, "link", "set", "lo", "up")

    def address(self, host: int) -> str:
        return SUBNET.format(tag=self.net, host=host)

    def run(self, host: int, args: list[str], env: dict[str, str]) -> subprocess.Popen[bytes]:
        process = subprocess.Popen(
            ["ip", "netns", "exec", self.hosts[host], sys.executable, *args],
            env={**os.environ, **env}, stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        self.processes.append(process)
        return process

    def close(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.terminate()
        for process in self.processes:
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
        for ns in (*self.hosts.values(), self.switch):
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True)


@pytest.fixture()
def lab() -> Iterator[Lab]:
    reason = _can_make_namespaces()
    if reason is not None:
        pytest.skip(reason)
    lab = Lab()
    try:
        yield lab
    finally:
        lab.close()


def _echo(lab: Lab, host: int, topic: str, env: dict[str, str], seconds: float) -> list[str]:
    """What ``dammrl echo`` on ``host`` prints within ``seconds`` (one message at most)."""
    watcher = lab.run(host, ["-m", "dammrl", "echo", topic, "--count", "1",
                             "--duration", str(seconds)], env)  # fmt: skip
    out, _ = watcher.communicate(timeout=seconds + 60)
    return [line for line in out.decode().splitlines() if line.startswith("{")]


def test_a_secured_stack_across_hosts_runs_and_an_outsider_gets_nothing(
    lab: Lab, tmp_path: Path
) -> None:
    credentials = tmp_path / "bus"
    create_credentials(credentials, [lab.address(h) for h in HOSTS])
    sim_endpoint = f"tls/{lab.address(1)}:7447"
    common = {"DAMMRL_BUS_CREDENTIALS": str(credentials), "DAMMRL_LOG_LEVEL": "WARNING",
              "DAMMRL_TASK_EPISODES": "1", "DAMMRL_CONTROLLER_TRIGGER": "fixed",
              "DAMMRL_POLICY_KIND": "fixed", "DAMMRL_POLICY_HUMAN_MODEL": "2",
              "DAMMRL_POLICY_ROBOT_MODEL": "1"}  # fmt: skip
    joined = {**common, "DAMMRL_BUS_CONNECT": json.dumps([sim_endpoint])}
    started = time.monotonic()
    lab.run(1, ["-m", "services.sim"], {**common, "DAMMRL_BUS_LISTEN": json.dumps([sim_endpoint])})
    for service in ("policy", "intent", "controller"):
        lab.run(2, ["-m", f"services.{service}"], joined)
    lab.run(3, ["-m", "services.recorder"], {**joined, "DAMMRL_RECORDER_OUT": str(tmp_path)})
    tool = {**joined, "DAMMRL_BUS_ROLE": "observer"}
    result = _echo(lab, 3, "task/result", tool, 120)
    elapsed = time.monotonic() - started
    assert result, "no episode result reached host 3"
    episode = json.loads(result[0])
    assert episode["outcome"] in ("success", "hold", "timeout") and episode["episode"] == 1
    print(f"\nfirst episode across hosts: {episode['outcome']} in {episode['t_total_s']:.1f} s "
          f"(robot time), result after {elapsed:.1f} s wall")  # fmt: skip
    outsider = {"DAMMRL_BUS_CONNECT": json.dumps([f"tcp/{lab.address(1)}:7447"])}
    assert _echo(lab, 4, "robot/state", outsider, 3) == []
    foreign = tmp_path / "foreign"
    create_credentials(foreign, [lab.address(4)])  # another CA, a 'tool' certificate
    assert _echo(lab, 4, "robot/state", {**joined, "DAMMRL_BUS_CREDENTIALS": str(foreign)}, 3) == []
    assert _echo(lab, 3, "robot/state", tool, 10), "a lab tool reads the arm's state"
