"""compose.yaml, checked without Docker: every service's command (and health check) runs
as written. tests/test_containers.py runs the real thing when a Docker engine is there."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from dammrl.devices.emulators.pad import DEFAULT_CALIBRATION
from schemas import EpisodeResult, Intent
from services.common.bus import Bus
from services.common.certificates import create_credentials
from services.common.config import BusSettings
from services.common.healthcheck import check
from tests.busutil import Observer, endpoint, free_port, start_patient, wait_for

pytestmark = pytest.mark.slow  # real processes on a real bus

COMPOSE = Path(__file__).resolve().parent.parent / "compose.yaml"
SERVICES = {"sim", "robot", "policy", "intent", "controller", "recorder"}
CONTAINER_PATHS = ("DAMMRL_PAD_PORT", "DAMMRL_PAD_CALIBRATION_FILE", "DAMMRL_RECORDER_OUT")
PROFILES = {
    "virtual": {"sim", "policy", "intent", "controller", "recorder"},
    "semi-virtual": {"sim", "policy", "intent-sensor", "controller-sensor", "recorder-sensor"},
    "real": {"robot", "policy-real", "intent-real", "controller-real", "recorder-real"},
}
MAY_MOVE_THE_ARM = {"sim", "robot", "controller"}
"""Restarted, they reset the arm and start an episode: never restarted on their own."""


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
        module = name.removesuffix("-sensor").removesuffix("-real")
        assert service["command"] == ["python", "-m", f"services.{module}"]
        assert all(k.startswith("DAMMRL_") for k in service["environment"])
        assert set(service.get("depends_on", {})) <= set(services), "compose refuses this"


@pytest.mark.parametrize("profile", PROFILES)
def test_each_service_starts_once_what_it_needs_is_healthy_and_the_controller_last(
    profile: str,
) -> None:
    services = _profile(profile)
    for name, service in services.items():
        check = service["healthcheck"]["test"]
        assert check == ["CMD", "python", "-m", "services.common.healthcheck", _bus_name(name)]
        needs = service.get("depends_on", {})
        assert all(n["condition"] == "service_healthy" for n in needs.values()), name
        arm = {"sim", "robot"}
        assert name in arm or arm & set(needs), name  # the arm's service is the hub
    name, controller = next((n, s) for n, s in services.items() if n.startswith("controller"))
    assert set(controller["depends_on"]) == set(services) - {name}


def test_services_that_would_move_the_arm_are_never_restarted_the_others_are() -> None:
    for name, service in _compose()["services"].items():
        expected = "no" if _bus_name(name) in MAY_MOVE_THE_ARM else "on-failure"
        assert service["restart"] == expected, name


def test_services_run_as_the_host_user_not_root() -> None:
    for name, service in _compose()["services"].items():
        assert service["user"] == "${DAMMRL_UID:-1000}:${DAMMRL_GID:-1000}", name


def _bus_name(container: str) -> str:
    return container.removesuffix("-sensor").removesuffix("-real")


@pytest.mark.parametrize("profile", PROFILES)
def test_every_container_joins_the_secured_bus_with_its_own_roles_credentials_only(
    profile: str,
) -> None:
    """The lab CA, the service's own certificate and the observer's (its health check):
    never another role's, so no container holds the operator's key (a stop's release)."""
    for name, service in _profile(profile).items():
        env = service["environment"]
        endpoints = json.loads(env.get("DAMMRL_BUS_CONNECT") or env["DAMMRL_BUS_LISTEN"])
        assert all(e.startswith("tls/") for e in endpoints), name
        role = _bus_name(name)
        wanted = {"ca.pem", f"{role}.pem", f"{role}.key", "observer.pem", "observer.key"}
        assert _credential_files(service) == wanted, name
        for volume in service["volumes"]:
            if volume["source"].startswith("./bus/"):
                assert volume["read_only"], name
                assert (
                    volume["target"]
                    == f"{env['DAMMRL_BUS_CREDENTIALS']}/" + Path(volume["source"]).name
                ), name


def _credential_files(service: dict[str, Any]) -> set[str]:
    """The files of ./bus (from `dammrl bus init`) mounted into a container."""
    sources = [Path(v["source"]) for v in service["volumes"]]
    return {s.name for s in sources if s.parent == Path("bus")}


def test_host_folders_are_mounted_only_when_they_exist_never_created_root_owned() -> None:
    for name, service in _compose()["services"].items():
        for volume in service["volumes"]:
            assert volume["type"] == "bind" and volume["source"].startswith("./"), name
            assert volume["bind"] == {"create_host_path": False}, name


def test_semi_virtual_profile_passes_the_sensor_and_its_calibration_to_the_intent() -> None:
    intent = _profile("semi-virtual")["intent-sensor"]
    env = intent["environment"]
    assert env["DAMMRL_INTENT_SOURCE"] == "pad"
    host, container = intent["devices"][0].rsplit(":", 1)
    assert container == env["DAMMRL_PAD_PORT"] and "DAMMRL_SENSOR_DEVICE" in host
    mounts = [volume["target"] for volume in intent["volumes"]]
    assert any(env["DAMMRL_PAD_CALIBRATION_FILE"].startswith(m + "/") for m in mounts)
    recorder = _profile("semi-virtual")["recorder-sensor"]["environment"]
    assert recorder["DAMMRL_RECORDER_MODE"] == "semi-virtual"


def test_real_profile_passes_the_servo_bus_and_the_arm_calibration_to_the_robot() -> None:
    robot = _profile("real")["robot"]
    env = robot["environment"]
    host, container = robot["devices"][0].rsplit(":", 1)
    assert container == env["DAMMRL_DYNAMIXEL_PORT"] and "DAMMRL_ROBOT_DEVICE" in host
    mounts = [volume["target"] for volume in robot["volumes"]]
    assert any(env["DAMMRL_DYNAMIXEL_CALIBRATION_FILE"].startswith(m + "/") for m in mounts)
    assert _profile("real")["recorder-real"]["environment"]["DAMMRL_RECORDER_MODE"] == "real"


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
    """The container environment on this machine: endpoints on loopback (the sim's port
    for the stack, a free one for each other listening service), paths in tmp."""
    local = {}
    connects = "DAMMRL_BUS_CONNECT" in environment
    for name, value in environment.items():
        if name in ("DAMMRL_BUS_CONNECT", "DAMMRL_BUS_LISTEN"):
            scheme = json.loads(value)[0].split("/")[0]
            own = name == "DAMMRL_BUS_LISTEN" and connects  # not the sim: its own port
            value = json.dumps(
                [endpoint(free_port() if own else port).replace("tcp/", f"{scheme}/")]
            )
        elif name == "DAMMRL_BUS_CREDENTIALS":
            value = str(tmp_path / "bus")  # replaced by the container's own files
        elif name in (
            "DAMMRL_PAD_PORT",
            "DAMMRL_PAD_CALIBRATION_FILE",
            "DAMMRL_RECORDER_OUT",
            "DAMMRL_DYNAMIXEL_PORT",
            "DAMMRL_DYNAMIXEL_CALIBRATION_FILE",
        ):
            value = str(tmp_path / Path(value).name)
        local[name] = str(value)
    return local


def _mounted(service: dict[str, Any], credentials: Path, folder: Path) -> Path:
    """A folder holding only the credential files compose mounts into the container."""
    folder.mkdir(mode=0o700)
    for name in _credential_files(service):
        shutil.copy2(credentials / name, folder / name)  # keys stay 0600
    return folder


def _health(
    command: list[str], env: dict[str, str], tries: int
) -> subprocess.CompletedProcess[str]:
    """The health check as compose runs it: passed, or failed ``tries`` times in a row (its
    ``retries``; 2 s apart here, compose waits its ``interval``): a pad silent for a second
    on a busy PC is degraded for that second, and says so."""
    for attempt in range(tries):
        done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=60)
        if done.returncode == 0 or attempt == tries - 1:
            return done
        time.sleep(2.0)
    raise AssertionError("no health check ran")


def _run_profile(profile: str, tmp_path: Path, patient: bool = False) -> Observer:
    """Start every container command of the profile as a process; run one episode (with a
    simulated patient at an emulated pad for the sensor); then every health check passes."""
    port, credentials = free_port(), tmp_path / "bus"
    create_credentials(credentials)  # what `dammrl bus init --out bus --host sim` makes
    processes = [start_patient(tmp_path / "ttySENSOR", port, 2, credentials)] if patient else []
    observer, checks = None, {}
    try:
        for name, service in _profile(profile).items():
            env = _path_env() | _local(service["environment"], port, tmp_path)
            env["DAMMRL_BUS_CREDENTIALS"] = str(_mounted(service, credentials, tmp_path / name))
            env["DAMMRL_TASK_EPISODES"] = "1"
            processes.append(subprocess.Popen(service["command"], env=env))
            health = service["healthcheck"]
            checks[name] = (health["test"][1:], env, int(health["retries"]))
            if observer is None:  # the sim listens: the test joins as one more peer
                time.sleep(1.0)
                observer = Observer(port, connect=True, credentials=credentials)
        assert observer is not None
        wait_for(lambda: bool(observer.of(EpisodeResult)), 120, "an EpisodeResult")
        assert all(p.poll() is None for p in processes)
        for name, (command, env, retries) in checks.items():
            done = _health(command, env, retries)
            assert done.returncode == 0, f"{name}: {done.stdout}{done.stderr}"
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
    assert all(
        isinstance(i, Intent) and i.source == "pad" and i.person for i in observer.of(Intent)
    )


def test_the_real_profile_runs_an_episode_on_the_passed_through_servo_bus(
    tmp_path: Path,
) -> None:
    """The emulated arm stands in for the device at the robot's DAMMRL_DYNAMIXEL_PORT: its
    own process at the servos' priority (`dammrl robot emulate`), as a lab runs it."""
    from dammrl_core.arm.dynamixel.calibration import Calibration, save_calibration

    save_calibration(Calibration(), tmp_path / "arm_calibration.json")
    link = tmp_path / "ttyROBOT"
    arm = subprocess.Popen([sys.executable, "-m", "dammrl", "robot", "emulate", "--port",
                            str(link)], stdin=subprocess.DEVNULL)  # fmt: skip
    try:
        wait_for(link.exists, 30, "the emulated servo bus")
        observer = _run_profile("real", tmp_path)
    finally:
        arm.terminate()
        arm.wait(15)
    assert observer.of(EpisodeResult)
    assert list((tmp_path / "sessions").glob("*.mcap")), "the recorder wrote the session"


def test_the_health_check_fails_with_its_reason_when_the_service_is_not_there(
    tmp_path: Path,
) -> None:
    create_credentials(tmp_path / "bus")
    env = _path_env() | {
        "DAMMRL_BUS_LISTEN": json.dumps([endpoint(free_port()).replace("tcp/", "tls/")]),
        "DAMMRL_BUS_CREDENTIALS": str(tmp_path / "bus"),
    }
    command = _profile("virtual")["policy"]["healthcheck"]["test"][1:]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and done.stdout.startswith("cannot join the bus at"), done


def test_a_holding_service_is_healthy_and_a_degraded_one_is_not(tmp_path: Path) -> None:
    create_credentials(tmp_path / "bus")
    listen = [endpoint(free_port()).replace("tcp/", "tls/")]
    settings = BusSettings(listen=listen, credentials=tmp_path / "bus")
    with Bus(settings, "recorder") as bus:
        bus.declare_alive()
        for state, problem in (("holding", None), ("degraded", "recorder reports degraded: full")):
            stop = threading.Event()
            reporter = threading.Thread(target=_report, args=(bus, state, stop))
            reporter.start()
            try:
                assert check(settings, "recorder", timeout_s=5.0) == problem
            finally:
                stop.set()
                reporter.join()


def _report(bus: Bus, state: str, stop: threading.Event) -> None:
    while not stop.wait(0.1):
        bus.report_health(state, "full" if state == "degraded" else "", force=True)
