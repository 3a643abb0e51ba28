"""compose.yaml, checked without Docker: every service's command runs as written."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from schemas import EpisodeResult, Intent
from services.common.security import create_credentials
from services.intent.emulator import DEFAULT_CALIBRATION
from tests.busutil import Observer, endpoint, free_port, start_patient, wait_for

pytestmark = pytest.mark.slow  # real processes on a real bus

COMPOSE = Path(__file__).resolve().parent.parent / "compose.yaml"
SERVICES = {"sim", "policy", "intent", "controller", "recorder"}
CONTAINER_PATHS = ("DAMMRL_INTENT_PORT", "DAMMRL_INTENT_CALIBRATION_FILE", "DAMMRL_RECORDER_OUT")
PROFILES = {
    "virtual": {"sim", "policy", "intent", "controller", "recorder"},
    "semi-virtual": {"sim", "policy", "intent-sensor", "controller", "recorder-sensor"},
}


def _compose() -> dict[str, Any]:
    document = yaml.safe_load(COMPOSE.read_text())
    assert isinstance(document, dict)
    return document


def _profile(name: str) -> dict[str, dict[str, Any]]:
    services = _compose()["services"]
    return {k: v for k, v in services.items() if name in v.get("profiles", [])}


@pytest.mark.parametrize("profile", PROFILES)
def test_each_profile_has_one_container_per_service_from_one_image(profile: str) -> None:
    services = _profile(profile)
    assert set(services) == PROFILES[profile]
    assert {s["image"] for s in services.values()} == {"dammrl:latest"}
    for name, service in services.items():
        module = name.removesuffix("-sensor")
        assert service["command"] == ["python", "-m", f"services.{module}"]
        assert all(k.startswith("DAMMRL_") for k in service["environment"])
        assert set(service.get("depends_on", [])) <= set(services), "compose refuses this"


@pytest.mark.parametrize("profile", PROFILES)
def test_every_container_joins_the_secured_bus_with_the_mounted_credentials(profile: str) -> None:
    for name, service in _profile(profile).items():
        env = service["environment"]
        endpoints = json.loads(env.get("DAMMRL_BUS_CONNECT") or env["DAMMRL_BUS_LISTEN"])
        assert all(e.startswith("tls/") for e in endpoints), name
        assert f"./bus:{env['DAMMRL_BUS_CREDENTIALS']}:ro" in service["volumes"], name


def test_semi_virtual_profile_passes_the_sensor_and_its_calibration_to_the_intent() -> None:
    intent = _profile("semi-virtual")["intent-sensor"]
    env = intent["environment"]
    assert env["DAMMRL_INTENT_SOURCE"] == "serial"
    host, container = intent["devices"][0].rsplit(":", 1)
    assert container == env["DAMMRL_INTENT_PORT"] and "DAMMRL_SENSOR_DEVICE" in host
    mounts = [volume.split(":")[1] for volume in intent["volumes"]]
    assert any(env["DAMMRL_INTENT_CALIBRATION_FILE"].startswith(m + "/") for m in mounts)
    recorder = _profile("semi-virtual")["recorder-sensor"]["environment"]
    assert recorder["DAMMRL_RECORDER_MODE"] == "semi-virtual"


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


def _local(environment: dict[str, str], port: int, tmp_path: Path) -> dict[str, str]:
    """The container environment on this machine: endpoints on loopback, paths in tmp."""
    local = {}
    for name, value in environment.items():
        if name in ("DAMMRL_BUS_CONNECT", "DAMMRL_BUS_LISTEN"):
            scheme = json.loads(value)[0].split("/")[0]
            value = json.dumps([endpoint(port).replace("tcp/", f"{scheme}/")])
        elif name == "DAMMRL_BUS_CREDENTIALS":
            value = str(tmp_path / "bus")
        elif name in (
            "DAMMRL_INTENT_PORT",
            "DAMMRL_INTENT_CALIBRATION_FILE",
            "DAMMRL_RECORDER_OUT",
        ):
            value = str(tmp_path / Path(value).name)
        local[name] = str(value)
    return local


def _run_profile(profile: str, tmp_path: Path, patient: bool = False) -> Observer:
    """Start every container command of the profile as a process; run one episode (with a
    simulated patient at an emulated pad for the sensor)."""
    port, credentials = free_port(), tmp_path / "bus"
    create_credentials(credentials)  # what `dammrl bus init --out bus --host sim` makes
    processes = [start_patient(tmp_path / "ttySENSOR", port, 2, credentials)] if patient else []
    observer = None
    try:
        for service in _profile(profile).values():
            env = _path_env() | _local(service["environment"], port, tmp_path)
            env["DAMMRL_TASK_EPISODES"] = "1"
            processes.append(subprocess.Popen(service["command"], env=env))
            if observer is None:  # the sim listens: the test joins as one more peer
                time.sleep(1.0)
                observer = Observer(port, connect=True, credentials=credentials)
        assert observer is not None
        wait_for(lambda: bool(observer.of(EpisodeResult)), 120, "an EpisodeResult")
        assert all(p.poll() is None for p in processes)
        return observer
    finally:
        for process in processes:
            process.terminate()
        for process in processes:
            process.wait(15)
        if observer is not None:
            observer.close()


def test_the_virtual_profile_comes_up_and_runs_an_episode_with_its_own_commands(
    tmp_path: Path,
) -> None:
    _run_profile("virtual", tmp_path)
    assert list((tmp_path / "sessions").glob("*.mcap")), "the recorder wrote the session"


def test_the_semi_virtual_profile_runs_an_episode_from_the_passed_through_sensor(
    tmp_path: Path,
) -> None:
    (tmp_path / "sensor_calibration.json").write_text(DEFAULT_CALIBRATION.model_dump_json())
    observer = _run_profile("semi-virtual", tmp_path, patient=True)
    result = observer.of(EpisodeResult)[0]
    assert isinstance(result, EpisodeResult) and result.success, result.reason
    assert all(isinstance(i, Intent) and i.source == "sensor" for i in observer.of(Intent))
