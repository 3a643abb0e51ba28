"""compose.yaml, checked without Docker: every service's command runs as written."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from schemas import EpisodeResult
from tests.busutil import Observer, endpoint, free_port, wait_for

COMPOSE = Path(__file__).resolve().parent.parent / "compose.yaml"
SERVICES = {"sim", "policy", "intent", "controller"}


def _compose() -> dict[str, Any]:
    document = yaml.safe_load(COMPOSE.read_text())
    assert isinstance(document, dict)
    return document


def _profile(name: str) -> dict[str, dict[str, Any]]:
    services = _compose()["services"]
    return {k: v for k, v in services.items() if name in v.get("profiles", [])}


def test_virtual_profile_has_one_container_per_service_from_one_image() -> None:
    services = _profile("virtual")
    assert set(services) == SERVICES
    assert {s["image"] for s in services.values()} == {"dammrl:latest"}
    for name, service in services.items():
        assert service["command"] == ["python", "-m", f"services.{name}"]
        assert all(k.startswith("DAMMRL_") for k in service["environment"])


def test_every_service_answers_help() -> None:
    for name in SERVICES:
        done = subprocess.run(
            ["python", "-m", f"services.{name}", "--help"], capture_output=True, text=True,
            timeout=60, check=False, env=_path_env(),
        )  # fmt: skip
        assert done.returncode == 0 and "DAMMRL_BUS_" in done.stdout


def _path_env() -> dict[str, str]:
    """This interpreter first on PATH: `python` in the commands is the image's Python."""
    return dict(os.environ) | {
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"
    }


def _local(environment: dict[str, str], port: int) -> dict[str, str]:
    """The container environment with the stack's endpoints moved to loopback."""
    local = {}
    for name, value in environment.items():
        if name in ("DAMMRL_BUS_CONNECT", "DAMMRL_BUS_LISTEN"):
            value = json.dumps([endpoint(port)])
        local[name] = str(value)
    return local


def test_the_virtual_profile_comes_up_and_runs_an_episode_with_its_own_commands() -> None:
    port = free_port()
    processes = []
    observer = None
    try:
        for service in _profile("virtual").values():
            env = _path_env() | _local(service["environment"], port)
            env["DAMMRL_TASK_EPISODES"] = "1"
            processes.append(subprocess.Popen(service["command"], env=env))
            if observer is None:  # the sim listens: the test joins as one more peer
                time.sleep(1.0)
                observer = Observer(port, connect=True)
        assert observer is not None
        wait_for(lambda: bool(observer.of(EpisodeResult)), 90, "an EpisodeResult")
        assert all(p.poll() is None for p in processes)
    finally:
        for process in processes:
            process.terminate()
        for process in processes:
            process.wait(15)
        if observer is not None:
            observer.close()
