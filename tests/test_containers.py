"""The image and compose.yaml for real: build, `up` the virtual profile, episodes, `down`.

Needs a running Docker engine with Compose v2 and the Dockerfile's base image present;
without them the test skips and says which is missing, or fails where
DAMMRL_TEST_REQUIRE_ENGINE=1 (CI: .ci/run starts the engine with
`../shared/tools/container-engine start`; the test never starts one). Extra build
arguments come from DAMMRL_TEST_BUILD_ARGS, e.g. the local wheel server's:
    DAMMRL_TEST_BUILD_ARGS="$(container-engine wheels)" pytest -m slow tests/test_containers.py
without them the Dockerfile's default torch index must be reachable (else: skipped). With
a warm build cache (the same build arguments) it takes about a minute.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import re
import shlex
import shutil
import subprocess
import time
import tomllib
import urllib.request
import uuid
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from dammrl.stack.recording import info, read_recording
from dammrl_core.intent.pad.calibration import DEFAULT_CALIBRATION
from schemas import Intent
from services.common.certificates import create_credentials
from tests.busutil import free_port, start_patient

pytestmark = pytest.mark.slow  # builds an image and runs five containers

ROOT = Path(__file__).resolve().parent.parent
EPISODES = 2
NON_ROOT = (1000, 1000)
"""Who the services run as when the test runs as root: a host user's files, as a lab has."""
BUILD_TIMEOUT_S, UP_TIMEOUT_S, EPISODES_TIMEOUT_S = 1800, 300, 180
BUILD_FILES = ("pyproject.toml", "README.md", "docker/check_image.py")
"""What the build reads besides the package folders (.dockerignore admits them by name)."""
REQUIRED = os.environ.get("DAMMRL_TEST_REQUIRE_ENGINE") == "1"
"""CI sets it (.ci/run starts an engine): a missing engine there fails, never skips."""
_spec = importlib.util.spec_from_file_location("check_image", ROOT / "docker/check_image.py")
assert _spec is not None and _spec.loader is not None
CHECK = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(CHECK)


def _ok(*command: str, timeout_s: float = 20) -> bool:
    try:
        done = subprocess.run(command, capture_output=True, timeout=timeout_s, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _base_images() -> list[str]:
    dockerfile = (ROOT / "Dockerfile").read_text()
    return sorted(set(re.findall(r"^FROM\s+(\S+)", dockerfile, re.MULTILINE)))


def _build_args() -> list[str]:
    return shlex.split(os.environ.get("DAMMRL_TEST_BUILD_ARGS", ""))


def _default_index_unreachable() -> str | None:
    """The Dockerfile's default torch index, when this machine cannot reach it (pip would
    retry for many minutes, then take PyPI's CUDA torch, which the build refuses)."""
    dockerfile = (ROOT / "Dockerfile").read_text()
    index = re.search(r"^ARG PIP_EXTRA_INDEX_URL=(\S+)", dockerfile, re.MULTILINE)
    assert index is not None, "the Dockerfile names its torch index"
    try:
        with urllib.request.urlopen(index[1], timeout=10):
            return None
    except (OSError, ValueError):
        return index[1]


def _engine_missing() -> str | None:
    """Why the real thing cannot run here, or None."""
    if shutil.which("docker") is None:
        return "no docker CLI on PATH"
    if not _ok("docker", "info"):
        return (
            "no Docker engine answers `docker info` (this test does not start one; here: "
            "../shared/tools/container-engine start)"
        )
    if not _ok("docker", "compose", "version"):
        return "no Docker Compose v2 (`docker compose version` fails)"
    for base in _base_images():
        if not _ok("docker", "image", "inspect", base):
            return f"the base image {base} is not present (the test pulls nothing)"
    if not any(a.startswith("PIP_EXTRA_INDEX_URL=") for a in _build_args()):
        index = _default_index_unreachable()
        if index is not None:
            return (
                f"torch's index {index} is unreachable and DAMMRL_TEST_BUILD_ARGS names no "
                'other (here: DAMMRL_TEST_BUILD_ARGS="$(container-engine wheels)")'
            )
    return None


def test_the_skip_looks_for_the_dockerfiles_own_base_image() -> None:
    assert _base_images() == ["python:3.11-slim"]


def test_the_build_context_holds_every_package_pip_installs() -> None:
    """.dockerignore re-admits exactly pyproject.toml's package patterns (and the files the
    build reads): a new top-level package cannot be left out of the image again."""
    allowed = [line[1:] for line in (ROOT / ".dockerignore").read_text().splitlines()
               if line.startswith("!")]  # fmt: skip
    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    packages = [p for p in allowed if p not in BUILD_FILES]
    assert sorted(packages) == sorted(find["find"]["include"])
    assert all((ROOT / f).is_file() for f in BUILD_FILES) and set(BUILD_FILES) <= set(allowed)


def test_the_image_check_names_a_file_the_wheel_lacks(tmp_path: Path) -> None:
    (tmp_path / "pkg" / "data").mkdir(parents=True)
    for name in ("pkg/__init__.py", "pkg/data/arm.urdf", "pkg/data/policy.pt"):
        (tmp_path / name).write_text("x")
    wheel = tmp_path / "pkg.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        archive.writestr("pkg/__init__.py", "x")
        archive.writestr("pkg/data/arm.urdf", "x")
    assert CHECK.check_wheel(wheel, tmp_path) == ["pkg/data/policy.pt is not in the wheel"]


def test_the_image_check_names_a_module_that_does_not_import(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "brokenpkg").mkdir()
    (tmp_path / "brokenpkg" / "__init__.py").write_text("")
    (tmp_path / "brokenpkg" / "good.py").write_text("VALUE = 1\n")
    (tmp_path / "brokenpkg" / "bad.py").write_text("import libgomp_is_missing\n")
    (tmp_path / "brokenpkg" / "__main__.py").write_text("raise SystemExit('ran')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    (problem,) = CHECK._import_all("brokenpkg")
    assert problem.startswith("brokenpkg.bad: ModuleNotFoundError")


@pytest.fixture(scope="module")
def image() -> Iterator[str]:
    """This checkout's image under a temporary tag, built once for the module."""
    missing = _engine_missing()
    if missing is not None:
        if REQUIRED:
            pytest.fail(f"DAMMRL_TEST_REQUIRE_ENGINE=1 but {missing}")
        pytest.skip(missing)
    tag = f"dammrl:test-{uuid.uuid4().hex[:8]}"
    try:
        _build(tag)
        yield tag
    finally:
        subprocess.run(["docker", "image", "rm", "--no-prune", tag], capture_output=True)


def test_the_virtual_profile_runs_episodes_in_containers_recorded_as_the_host_user(
    image: str, tmp_path: Path
) -> None:
    with _stack(tmp_path, image, "virtual") as compose:
        _wait_for_episodes(compose, "controller")
        states = _states(compose)
        assert all(s["Health"] == "healthy" for s in states.values()), states
    _assert_recorded(tmp_path)


def test_the_semi_virtual_profile_runs_episodes_from_an_emulated_pad_in_containers(
    image: str, tmp_path: Path
) -> None:
    """The pad emulator runs on the host (a pty, a simulated patient answering the
    stack's decision requests over the sim's published port); the pty is bind-mounted at
    the intent's DAMMRL_PAD_PORT where a lab's compose passes the device."""
    port = free_port()
    (tmp_path / "calibration").mkdir()
    (tmp_path / "calibration" / "sensor_calibration.json").write_text(
        DEFAULT_CALIBRATION.model_dump_json()
    )
    create_credentials(tmp_path / "bus")
    pad = tmp_path / "ttyPAD"
    patient = start_patient(pad, port, 1, tmp_path / "bus")
    try:
        device = pad.resolve()
        os.chmod(device, 0o666)  # the services' user opens it, as `dialout` would
        extra = _semi_virtual_override(device, port)
        with _stack(tmp_path, image, "semi-virtual", extra) as compose:
            _wait_for_episodes(compose, "controller-sensor")
            states = _states(compose)
            assert all(s["Health"] == "healthy" for s in states.values()), states
            intents = _logs(compose, "intent-sensor")
        assert patient.poll() is None, "the emulated pad and patient stayed up"
    finally:
        patient.terminate()
        patient.wait(15)
    _assert_recorded(tmp_path, intent_source="pad")
    assert "Traceback" not in intents, intents


def _semi_virtual_override(device: Path, port: int) -> dict[str, list[str]]:
    """Override lines per service: the pty instead of a device, the sim's port on
    loopback for the host's emulator."""
    mount = (f"      - {{type: bind, source: {device}, target: /dev/ttySENSOR, "
             "bind: {create_host_path: false}}")  # fmt: skip
    return {
        "intent-sensor": ["    devices: !reset []", "    volumes:", mount],
        "sim": ["    ports: !override", f'      - "127.0.0.1:{port}:7447"'],
    }


def _assert_recorded(work: Path, intent_source: str | None = None) -> None:
    """One complete MCAP with every episode's result, owned by the host user."""
    (session,) = (work / "sessions").glob("*.mcap")
    summary = info(session)
    assert summary["complete"], summary["truncated"]
    assert summary["topics"]["dammrl/task/result"]["count"] >= EPISODES
    if intent_source is not None:
        intents = [m for _, m in read_recording(session).decoded(Intent)]
        assert intents and all(isinstance(i, Intent) and i.source == intent_source for i in intents)
    assert (session.stat().st_uid, session.stat().st_gid) == _user()


def _build(tag: str) -> None:
    """The image from this checkout (``--no-prune`` at removal keeps the build cache)."""
    done = subprocess.run(
        ["docker", "build", "-t", tag, *_build_args(), str(ROOT)],
        capture_output=True, text=True, timeout=BUILD_TIMEOUT_S, check=False,
    )  # fmt: skip
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]


def _user() -> tuple[int, int]:
    return NON_ROOT if os.getuid() == 0 else (os.getuid(), os.getgid())


@contextlib.contextmanager
def _stack(
    work: Path, tag: str, profile: str, extra: dict[str, list[str]] | None = None
) -> Iterator[list[str]]:
    """The profile up in ``work`` (compose.yaml, credentials, sessions), as the host user
    would run it; always taken down, volumes included."""
    shutil.copy(ROOT / "compose.yaml", work / "compose.yaml")
    (work / "test.yaml").write_text(_override(tag, profile, extra or {}))
    if not (work / "bus").exists():
        create_credentials(work / "bus")  # what `dammrl bus init --out bus --host sim` makes
    (work / "sessions").mkdir()
    uid, gid = _user()
    for path in (work / "bus", *(work / "bus").iterdir(), work / "sessions"):
        os.chown(path, uid, gid)  # a no-op unless the test runs as root
    compose = [
        "docker", "compose", "-p", f"dammrl-test-{uuid.uuid4().hex[:8]}",
        "--project-directory", str(work), "-f", str(work / "compose.yaml"),
        "-f", str(work / "test.yaml"), "--profile", profile,
    ]  # fmt: skip
    env = dict(os.environ) | {"DAMMRL_UID": str(uid), "DAMMRL_GID": str(gid)}
    try:
        up = subprocess.run(
            [*compose, "up", "-d", "--no-build", "--wait", "--wait-timeout", str(UP_TIMEOUT_S)],
            capture_output=True, text=True, timeout=UP_TIMEOUT_S + 60, env=env, check=False,
        )  # fmt: skip
        assert up.returncode == 0, up.stderr[-2000:] + _logs(compose)
        yield compose
    finally:
        subprocess.run(
            [*compose, "down", "-v", "--remove-orphans", "--timeout", "20"],
            capture_output=True, timeout=120, env=env, check=False,
        )  # fmt: skip


def _override(tag: str, profile: str, extra: dict[str, list[str]]) -> str:
    """This run's image for every service of the profile; no port published (no clash
    with a stack on this host) unless ``extra`` (lines per service) says otherwise. Text:
    PyYAML cannot write Compose's ``!reset`` tag."""
    services = yaml.safe_load((ROOT / "compose.yaml").read_text())["services"]
    lines = ["services:"]
    for name, service in services.items():
        if profile in service["profiles"]:
            lines += [f"  {name}:", f"    image: {tag}", "    pull_policy: never"]
            if "ports" in service and not any("ports:" in x for x in extra.get(name, [])):
                lines.append("    ports: !reset []")
            lines += extra.get(name, [])
    return "\n".join(lines) + "\n"


def _wait_for_episodes(compose: list[str], controller: str) -> None:
    deadline = time.monotonic() + EPISODES_TIMEOUT_S
    while time.monotonic() < deadline:
        if len(re.findall(r"episode \d+: ", _logs(compose, controller))) >= EPISODES:
            return
        time.sleep(5)
    raise AssertionError(f"fewer than {EPISODES} episodes ended\n{_logs(compose)}")


def _states(compose: list[str]) -> dict[str, dict[str, Any]]:
    done = subprocess.run(
        [*compose, "ps", "--format", "json"], capture_output=True, text=True, check=True
    )
    rows = [json.loads(line) for line in done.stdout.splitlines() if line.strip()]
    return {row["Service"]: row for row in rows}


def _logs(compose: list[str], *services: str) -> str:
    done = subprocess.run(
        [*compose, "logs", "--no-color", "--tail", "200", *services],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    return done.stdout + done.stderr
