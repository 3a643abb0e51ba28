"""The image and compose.yaml for real: build, `up` the virtual profile, episodes, `down`.

Needs a running Docker engine with Compose v2 and the Dockerfile's base image present;
without them the test skips and says which is missing (it never starts an engine: on
this kind of machine `../shared/tools/container-engine start` does). Extra build
arguments come from DAMMRL_TEST_BUILD_ARGS, e.g. the local wheel server's:
    DAMMRL_TEST_BUILD_ARGS="$(container-engine wheels)" pytest -m slow tests/test_containers.py
without them the Dockerfile's default torch index must be reachable (else: skipped). With
a warm build cache (the same build arguments) it takes about a minute.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import subprocess
import tempfile
import time
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from dammrl.recording import info
from services.common.certificates import create_credentials

pytestmark = pytest.mark.slow  # builds an image and runs five containers

ROOT = Path(__file__).resolve().parent.parent
PROFILE = "virtual"
EPISODES = 2
NON_ROOT = (1000, 1000)
"""Who the services run as when the test runs as root: a host user's files, as a lab has."""
BUILD_TIMEOUT_S, UP_TIMEOUT_S, EPISODES_TIMEOUT_S = 1800, 300, 180


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


def test_the_build_context_holds_only_what_pip_installs() -> None:
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert ignored[ignored.index("*") + 1 :][:5] == [
        "!pyproject.toml", "!README.md", "!dammrl", "!schemas", "!services",
    ]  # fmt: skip


def test_the_virtual_profile_runs_episodes_in_containers_recorded_as_the_host_user() -> None:
    missing = _engine_missing()
    if missing is not None:
        pytest.skip(missing)
    run = uuid.uuid4().hex[:8]
    tag, work = f"dammrl:test-{run}", Path(tempfile.mkdtemp(prefix="dammrl-containers-"))
    try:
        _build(tag)
        with _stack(work, tag, f"dammrl-test-{run}") as compose:
            _wait_for_episodes(compose)
            states = _states(compose)
            assert all(s["Health"] == "healthy" for s in states.values()), states
        (session,) = (work / "sessions").glob("*.mcap")
        summary = info(session)
        assert summary["complete"], summary["truncated"]
        assert summary["topics"]["dammrl/task/result"]["count"] >= EPISODES
        assert (session.stat().st_uid, session.stat().st_gid) == _user()
    finally:
        subprocess.run(["docker", "image", "rm", "--no-prune", tag], capture_output=True)
        shutil.rmtree(work, ignore_errors=True)


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
def _stack(work: Path, tag: str, project: str) -> Iterator[list[str]]:
    """The stack up in ``work`` (compose.yaml, credentials, sessions), as the host user
    would run it; always taken down, volumes included."""
    shutil.copy(ROOT / "compose.yaml", work / "compose.yaml")
    (work / "test.yaml").write_text(_override(tag))
    create_credentials(work / "bus")  # what `dammrl bus init --out bus --host sim` makes
    (work / "sessions").mkdir()
    uid, gid = _user()
    for path in (work / "bus", *(work / "bus").iterdir(), work / "sessions"):
        os.chown(path, uid, gid)  # a no-op unless the test runs as root
    compose = [
        "docker", "compose", "-p", project, "--project-directory", str(work),
        "-f", str(work / "compose.yaml"), "-f", str(work / "test.yaml"), "--profile", PROFILE,
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


def _override(tag: str) -> str:
    """This run's image for every service; the sim's port not published (no clash with a
    stack on this host). Text: PyYAML cannot write Compose's ``!reset`` tag."""
    services = yaml.safe_load((ROOT / "compose.yaml").read_text())["services"]
    lines = ["services:"]
    for name, service in services.items():
        if PROFILE in service["profiles"]:
            lines += [f"  {name}:", f"    image: {tag}", "    pull_policy: never"]
            lines += ["    ports: !reset []"] if "ports" in service else []
    return "\n".join(lines) + "\n"


def _wait_for_episodes(compose: list[str]) -> None:
    deadline = time.monotonic() + EPISODES_TIMEOUT_S
    while time.monotonic() < deadline:
        if len(re.findall(r"episode \d+: ", _logs(compose, "controller"))) >= EPISODES:
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
