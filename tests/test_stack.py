"""The stack as real processes on a real Zenoh bus (loopback, one port per test)."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest

from dammrl_core.robot import RobotDescription
from dammrl_core.robot.description import DEFAULT_URDF
from schemas import TOPICS, EpisodeResult, GoalRefused, Health, RobotState, StepEvent, encode
from tests.busutil import SERVICES, Lines, Observer, Stack, free_port, wait_for
from tests.test_priority import may_raise_priority
from tests.test_schemas import EXAMPLES

pytestmark = pytest.mark.slow  # real processes on a real bus

LONG_EPISODE = {"DAMMRL_TASK_EPISODES": "1", "DAMMRL_TASK_EPISODE_TIMEOUT_S": "120"}


@pytest.fixture()
def port() -> int:
    return free_port()


@pytest.fixture()
def observer(port: int) -> Iterator[Observer]:
    observer = Observer(port)
    yield observer
    observer.close()


@pytest.fixture()
def stack(port: int, observer: Observer) -> Iterator[Stack]:
    running = Stack(port, **LONG_EPISODE)
    yield running
    running.stop()


def _steps(observer: Observer) -> int:
    return len(observer.of(StepEvent))


def test_dammrl_up_runs_episodes_and_exits_zero(port: int) -> None:
    command = [sys.executable, "-m", "dammrl.cli", "up", "--episodes", "1", "--json",
               "--bus-port", str(port), "--model", "2,1"]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=180, check=False)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["success"], (result, done.stderr[-3000:])
    assert result["model"] == [2, 1] and result["trigger"] == "event"
    assert {"t_total_s", "n_osc", "jerk_isj", "human_error_rate", "seed"} <= result.keys()


def _launch_until_alive(port: int) -> tuple[subprocess.Popen[str], list[str], Lines]:
    """`dammrl up` until it reports every service alive; its child pids."""
    launcher = subprocess.Popen(
        [sys.executable, "-m", "dammrl.cli", "up", "--bus-port", str(port)],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert launcher.stderr is not None
    said = Lines(launcher.stderr)  # drained from now on
    said.wait_for("all services alive", 60)
    children = subprocess.run(
        ["pgrep", "-P", str(launcher.pid)], capture_output=True, text=True, check=False
    ).stdout.split()
    return launcher, children, said


def _session_nice(pid: str) -> tuple[str, int] | None:
    """(the service's name, its session's nice under Linux's autogroup); None without."""
    try:
        autogroup = Path(f"/proc/{pid}/autogroup").read_text()
        command = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    name = next(a.decode() for a in command if a.startswith(b"services."))
    return name.split(".")[1], int(autogroup.split("nice")[1])


def test_dammrl_up_stops_every_service_on_sigterm(port: int) -> None:
    launcher, children, _ = _launch_until_alive(port)
    assert len(children) == 4
    # the arm's loop ahead of a busy PC: each service leads its own session, which Linux
    # shares the processors by first, so its session has the loop's priority too
    sessions = dict(filter(None, map(_session_nice, children)))
    if sessions and may_raise_priority():
        assert sessions == {"sim": -10, "controller": -10, "policy": 0, "intent": 0}
    launcher.send_signal(signal.SIGTERM)
    assert launcher.wait(30) == 0
    time.sleep(0.5)
    assert not [pid for pid in children if _running(pid)]


def test_killed_controller_leaves_the_arm_held_and_a_new_one_resumes(
    stack: Stack, observer: Observer
) -> None:
    wait_for(lambda: _steps(observer) >= 3, 60, "the reach to start")
    stack.kill("controller")
    wait_for(lambda: any(m.holding for m in observer.of(RobotState)[-5:]), 5, "the sim to hold")
    held_from = len(observer.received)
    time.sleep(2.0)
    held = [m for m in observer.received[held_from:] if isinstance(m, RobotState)]
    positions = np.array([m.ee_pos_m for m in held])
    assert len(held) > 100
    assert np.max(np.linalg.norm(positions - positions[0], axis=1)) <= 0.005
    steps_before = _steps(observer)
    stack.restart("controller")
    wait_for(
        lambda: _steps(observer) > steps_before + 2 or bool(observer.of(EpisodeResult)),
        60,
        "the reach to resume",
    )


def test_killed_sim_makes_the_controller_report_stale_state(
    stack: Stack, observer: Observer
) -> None:
    wait_for(lambda: _steps(observer) >= 2, 60, "the reach to start")
    stack.kill("sim")
    wait_for(lambda: bool(observer.of(EpisodeResult)), 10, "the controller to give up")
    result = observer.of(EpisodeResult)[0]
    assert isinstance(result, EpisodeResult)
    assert result.outcome == "hold" and "stale" in result.reason
    time.sleep(1.0)
    assert stack.alive()["controller"]
    steps_after = _steps(observer)
    time.sleep(1.0)
    assert _steps(observer) == steps_after  # it stopped stepping


def test_episodes_the_arm_cannot_begin_end_as_holds_that_say_why_and_the_next_follows(
    port: int, observer: Observer, tmp_path: Path
) -> None:
    # the arm's machine has its elbow braced at 1.8 rad (its URDF says so), the controller's
    # model still allows 2.6 rad: every start posture it solves (elbow ~2 rad) is beyond it
    braced = tmp_path / "braced.urdf"
    braced.write_text(DEFAULT_URDF.read_text().replace('lower="0.0" upper="2.6"',
                                                       'lower="0.0" upper="1.8"'))  # fmt: skip
    sim = {"DAMMRL_ROBOT_URDF_PATH": str(braced)}
    stack = Stack(port, env_of={"sim": sim}, DAMMRL_TASK_EPISODES="2")
    try:
        wait_for(lambda: len(observer.of(EpisodeResult)) >= 2, 120, "both episodes to end")
        results = [m for m in observer.of(EpisodeResult) if isinstance(m, EpisodeResult)]
        assert [r.episode for r in results] == [1, 2]
        for result in results:
            assert result.outcome == "hold", result
            assert "the sim cannot begin it" in result.reason
            assert "outside the joint limits" in result.reason
        assert {m.episode for m in observer.of(GoalRefused) if isinstance(m, GoalRefused)} == {1, 2}
        assert not observer.of(StepEvent)  # nothing was begun
        elbow = [m.q_rad[3] for m in observer.of(RobotState) if isinstance(m, RobotState)]
        assert elbow and max(elbow) < 1.8
        assert all(stack.alive().values())
    finally:
        stack.stop()


def _fuzz_payloads(rng: random.Random) -> Iterator[tuple[type, bytes]]:
    robot = RobotDescription.from_urdf()
    bad_command = msgpack.unpackb(encode(EXAMPLES[1]))
    bad_command["header"]["source"] = "controller"  # spoofed: only the ranges can stop it
    for message_type in TOPICS.values():
        yield message_type, rng.randbytes(rng.randint(0, 200))
        yield message_type, msgpack.packb({"header": 1, "x": [1, 2, 3]})
        valid = next(m for m in EXAMPLES if isinstance(m, message_type))
        plain = msgpack.unpackb(encode(valid))
        field = next((k for k, v in plain.items() if isinstance(v, float | list)
                      and k != "header"), None)  # fmt: skip
        if field is None:
            continue  # nothing to make NaN (EmergencyStop)
        plain[field] = float("nan") if isinstance(plain[field], float) else [float("nan")] * 6
        yield message_type, msgpack.packb(plain)
    for episode in range(0, 3):
        for field, value in (
            ("q_ref_rad", list(robot.q_max + 0.5)),
            ("tau_ff_nm", list(robot.tau_max * 3)),
            ("kp_nm_per_rad", [1e5] * 6),
        ):
            yield type(EXAMPLES[1]), msgpack.packb(bad_command | {"episode": episode, field: value})


def test_fuzzing_every_key_leaves_every_service_alive_and_the_arm_in_its_limits(
    stack: Stack, observer: Observer
) -> None:
    wait_for(lambda: _steps(observer) >= 1, 60, "the reach to start")
    rng = random.Random(0)
    payloads = list(_fuzz_payloads(rng))
    end = time.monotonic() + 4.0
    sent = 0
    while time.monotonic() < end:
        message_type, payload = payloads[sent % len(payloads)]
        observer.put(message_type, payload)
        sent += 1
        time.sleep(0.001)
    time.sleep(1.5)
    assert all(stack.alive().values()), stack.alive()
    robot = RobotDescription.from_urdf()
    states = [m for m in observer.of(RobotState) if m.header.source == "sim"]
    q = np.array([m.q_rad for m in states])
    assert np.all(q >= robot.q_min - 0.02) and np.all(q <= robot.q_max + 0.02)
    rejected = {m.service: sum(m.rejected.values()) for m in observer.of(Health)}
    assert rejected.get("sim", 0) > 0 and rejected.get("controller", 0) > 0, rejected
    assert sent > 1000


def test_status_lists_every_service_and_echo_decodes_a_topic(
    stack: Stack, observer: Observer, port: int
) -> None:
    from dammrl.stack.inspect import echo, status
    from tests.busutil import client_settings

    wait_for(lambda: _steps(observer) >= 1, 60, "the reach to start")
    table, healthy = status(client_settings(port))
    assert healthy, table
    for name in SERVICES:
        assert any(line.split()[:2] == [name, "yes"] for line in table.splitlines()), table
    rate = re.search(r"robot/state (\d+) Hz", table)
    assert rate is not None and 80 <= int(rate.group(1)) <= 120, table
    lines: list[str] = []
    assert echo(client_settings(port), "robot/state", count=3, out=lines.append) == 3
    decoded = [json.loads(line) for line in lines]
    assert all(d["key"] == "dammrl/robot/state" and len(d["q_rad"]) == 6 for d in decoded)


def _dammrl(port: int, *args: str, timeout_s: float = 30) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "dammrl", *args, "--connect", f"tcp/127.0.0.1:{port}"]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, check=False)


def test_status_names_a_hung_service_and_a_dead_one_in_bounded_time(
    stack: Stack, observer: Observer, port: int
) -> None:
    wait_for(lambda: _steps(observer) >= 1, 60, "the reach to start")
    stack.processes["intent"].send_signal(signal.SIGSTOP)  # hung: alive, silent
    stack.kill("policy")  # dead
    try:
        started = time.monotonic()
        done = _dammrl(port, "status")
        took = time.monotonic() - started
    finally:
        stack.processes["intent"].send_signal(signal.SIGCONT)
    rows = {line.split()[0]: line.split()[1:3] for line in done.stdout.splitlines()[1:]}
    assert rows.get("intent") == ["yes", "silent"], done.stdout
    assert rows.get("policy") == ["NO", "missing"], done.stdout
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert took < 10, f"status took {took:.1f} s"  # start-up ~1.5 s + 0.3 + 1 + 2.5 listening


def test_echo_ends_cleanly_on_ctrl_c_and_says_when_nothing_came(
    stack: Stack, observer: Observer, port: int
) -> None:
    wait_for(lambda: _steps(observer) >= 1, 60, "the reach to start")
    command = [sys.executable, "-m", "dammrl", "echo", "robot/state",
               "--connect", f"tcp/127.0.0.1:{port}"]  # fmt: skip
    echo = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert echo.stdout is not None
    assert echo.stdout.readline().startswith("{")
    echo.send_signal(signal.SIGINT)
    _, err = echo.communicate(timeout=15)
    assert echo.returncode == 0 and "Traceback" not in err, err
    # a topic only a session publishes (task/result was quiet only if the reach did not end
    # in that second: on a loaded machine it did)
    quiet = _dammrl(port, "echo", "session/comfort", "--duration", "1")
    assert quiet.returncode == 1 and "nothing received on session/comfort" in quiet.stderr


def test_dammrl_up_exits_non_zero_when_a_service_dies(port: int) -> None:
    launcher, children, said = _launch_until_alive(port)
    os.kill(int(children[0]), signal.SIGKILL)
    assert launcher.wait(30) != 0
    said.wait_for("exited unexpectedly", 5)
    time.sleep(0.5)
    assert not [pid for pid in children[1:] if os.path.exists(f"/proc/{pid}")]


def test_a_stop_finds_the_runs_credentials_and_a_killed_launchers_services_and_keys_go(
    port: int,
) -> None:
    """`dammrl stop --connect tls/127.0.0.1:PORT` without --credentials stops the secured
    run on PORT; after `kill -9` of the launcher, every service exits within seconds and
    the run's credentials (every role's key) are removed by the last of them."""
    from services.common.security import run_credentials

    launcher, children, _ = _launch_until_alive(port)
    folder = run_credentials(port)
    assert (folder / "controller.key").is_file()
    for endpoint in (f"tls/127.0.0.1:{port}", f"tcp/127.0.0.1:{port}"):
        for flag in ((), ("--release",)):
            command = [sys.executable, "-m", "dammrl", "stop", "--connect", endpoint, *flag]
            done = subprocess.run(command, capture_output=True, text=True, timeout=30, check=False)
            assert done.returncode == 0 and "sim: " in done.stdout, done.stderr
    launcher.send_signal(signal.SIGKILL)
    launcher.wait(10)
    killed = time.monotonic()
    # ~2 s; a busy 2-core machine once took more than 10
    wait_for(lambda: not [p for p in children if _running(p)], 30, "every service to exit")
    print(f"services gone {time.monotonic() - killed:.1f} s after kill -9 of the launcher")
    wait_for(lambda: not folder.exists(), 10, "the run's credentials to be removed")


LAUNCHER_OF_ONE = """
import sys
from dammrl.stack import launch, options
options.MODES["virtual"] = ("intent",)  # the launcher as it is, with one quick service
sys.exit(launch.Stack(launch.StackOptions(port=int(sys.argv[1]))).run())
"""


def test_kill_9_of_the_launcher_removes_its_runs_keys_every_time() -> None:
    """After ``kill -9`` the parent-death signal comes as the launcher's main thread ends;
    its other threads end after it, and until the last has, a service still sees the
    launcher as its parent: one that stopped fast kept the keys (4 of 6 runs of
    ``dammrl up``). Ten runs, each killed with -9: the keys are gone every time."""
    from services.common.security import run_credentials

    kept = []
    for run in range(10):
        port = free_port()
        folder = run_credentials(port)
        launcher = subprocess.Popen([sys.executable, "-c", LAUNCHER_OF_ONE, str(port)],
                                    stdout=subprocess.PIPE, text=True)  # fmt: skip
        assert launcher.stdout is not None
        Lines(launcher.stdout).wait_for("all services alive", 60)
        children = subprocess.run(
            ["pgrep", "-P", str(launcher.pid)], capture_output=True, text=True, check=False
        ).stdout.split()
        assert (folder / "intent.key").is_file() and children
        launcher.send_signal(signal.SIGKILL)
        launcher.wait(10)
        wait_for(functools.partial(_none_running, children), 30, "the service to exit")
        if folder.exists():
            kept.append(run)
            shutil.rmtree(folder)
    assert not kept, f"the keys stayed after runs {kept} of 10"


def _none_running(pids: list[str]) -> bool:
    return not [pid for pid in pids if _running(pid)]


def _running(pid: str) -> bool:
    """Alive and not a zombie (an exited orphan whose new parent has not reaped it yet)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rpartition(")")[2].split()[0] != "Z"


def test_a_service_stuck_in_native_code_still_exits_on_sigterm(tmp_path: Path) -> None:
    """A main thread blocked on a futex never runs Python's signal handlers; the watcher
    of the signal's wakeup descriptor stops the process within its grace anyway."""
    script = tmp_path / "stuck.py"
    script.write_text(
        "import ctypes, threading\n"
        "from services.common.runtime import exit_within, stop_on_signals\n"
        "exit_within(stop_on_signals(), grace_s=1.0)\n"
        "libc = ctypes.CDLL(None)\n"
        "mutex = ctypes.create_string_buffer(64)\n"  # pthread_mutex_t, zeroed: unlocked
        "libc.pthread_mutex_lock(mutex)\n"
        "print('stuck', flush=True)\n"
        "libc.pthread_mutex_lock(mutex)\n"  # a default mutex locked twice: blocked forever
    )
    stuck = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                             env=os.environ | {"PYTHONPATH": os.getcwd()})  # fmt: skip
    assert stuck.stdout is not None and stuck.stdout.readline().strip() == "stuck"
    stuck.send_signal(signal.SIGTERM)
    started = time.monotonic()
    assert stuck.wait(10) == 128 + signal.SIGTERM
    assert time.monotonic() - started < 3.0


def test_a_signal_inside_the_stop_events_own_wait_still_stops_the_service(
    tmp_path: Path,
) -> None:
    """Python runs a handler in the main thread between bytecodes, also inside
    ``stop.wait()`` while that holds the event's lock: a handler that set the event there
    took the same lock and hung for ever (a service outlived its killed launcher so, and
    every signal after). Here the handler runs at exactly that point, on purpose."""
    script = tmp_path / "inside.py"
    script.write_text(
        "import signal\n"
        "from services.common.runtime import stop_on_signals\n"
        "stop = stop_on_signals()\n"
        "with stop._cond:\n"  # where Event.wait is when the signal comes
        "    stop.handle(signal.SIGTERM, None)\n"
        "    print('handled', flush=True)\n"
        "print('stopped' if stop.wait(5) else 'not stopped', stop.signum, flush=True)\n"
    )
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=30, env=os.environ | {"PYTHONPATH": os.getcwd()})  # fmt: skip
    assert done.stdout.split() == ["handled", "stopped", str(int(signal.SIGTERM))], done.stderr


def test_a_stopping_block_leaves_no_thread_and_no_descriptor_behind() -> None:
    from services.common.runtime import stopping_on_signals

    threads, fds = threading.active_count(), len(os.listdir("/proc/self/fd"))
    for _ in range(20):
        with stopping_on_signals() as stop:
            os.kill(os.getpid(), signal.SIGINT)
            assert stop.wait(5) and stop.signum == signal.SIGINT
    wait_for(lambda: threading.active_count() == threads, 5, "the setting threads to end")
    assert len(os.listdir("/proc/self/fd")) == fds
    assert signal.getsignal(signal.SIGINT) is not None  # pytest's own handler is back


def _full_pipe() -> tuple[int, int]:
    """A pipe whose buffer is full: a blocking write to its write end never returns."""
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    with contextlib.suppress(BlockingIOError):
        while True:
            os.write(write_end, b"x" * 4096)
    os.set_blocking(write_end, True)
    return read_end, write_end


@pytest.mark.parametrize("stopped_by", ["sigterm", "stop event"])
def test_a_service_whose_stderr_nobody_reads_still_exits_within_its_grace(
    tmp_path: Path, stopped_by: str
) -> None:
    """A launcher killed with -9 leaves its services' stderr a pipe nobody drains; once
    full, its writer thread holds the logging locks for ever (logging.shutdown at exit
    included). Whatever stops the service, it is gone within its grace."""
    script = tmp_path / "muted.py"
    script.write_text(
        "import sys\n"
        "from services.common.logs import setup_logging\n"
        "from services.common.runtime import exit_within, stop_on_signals\n"
        "stop = stop_on_signals()\n"
        "exit_within(stop, grace_s=1.0)\n"
        "setup_logging('muted').error('a line the full pipe never takes')\n"
        "print('ready', flush=True)\n"
        "if sys.argv[1] == 'stop event':\n"
        "    stop.set()\n"  # as the launcher's watch does: then a clean end, blocked at exit
        "stop.wait()\n"
    )
    read_end, write_end = _full_pipe()
    try:
        muted = subprocess.Popen([sys.executable, str(script), stopped_by], stdout=subprocess.PIPE,
                                 stderr=write_end, text=True,
                                 env=os.environ | {"PYTHONPATH": os.getcwd()})  # fmt: skip
        assert muted.stdout is not None and muted.stdout.readline().strip() == "ready"
        if stopped_by == "sigterm":
            muted.send_signal(signal.SIGTERM)
        started = time.monotonic()
        code = muted.wait(10)
        assert code == (128 + signal.SIGTERM if stopped_by == "sigterm" else 1)
        assert time.monotonic() - started < 4.0
    finally:
        os.close(read_end)
        os.close(write_end)
