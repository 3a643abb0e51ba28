"""`dammrl reach` as a user runs it."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from dammrl.cli import QUICK, main
from dammrl_core.errors import Exit
from tests.busutil import free_port

KEYS = {
    "success", "t_total_s", "t_step_mean_s", "final_error_m", "n_osc", "jerk_isj",
    "sparc", "ldlj", "human_error_rate", "n_steps", "trigger", "model", "seed",
}  # fmt: skip


def test_reach_json_has_the_promised_keys(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["reach", "--trigger", "fixed", "--model", "1,3", "--seed", "7", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result.keys() >= KEYS
    assert result["trigger"] == "fixed" and result["model"] == [1, 3] and result["seed"] == 7


def test_reach_table_shows_both_strategies(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["reach", "--trigger", "both", "--seed", "2"]) == 0
    out = capsys.readouterr().out
    header = out.splitlines()[0].split()
    assert header == ["metric", "fixed", "event"]
    assert "n_osc" in out and "t_total_s [s]" in out


def test_reach_plot_writes_a_png(tmp_path: Path) -> None:
    png = tmp_path / "reach.png"
    assert main(["reach", "--trigger", "both", "--seed", "1", "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("model", ["3,1", "1,9", "x"])
def test_bad_model_is_a_usage_error_naming_the_range(
    model: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["reach", "--model", model])
    assert exit_info.value.code == 2
    assert "must be" in capsys.readouterr().err


def test_bad_setting_from_the_environment_is_a_clear_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("DAMMRL_CONTROLLER_FIXED_PERIOD_S", "-1")
    assert main(["reach"]) == Exit.BAD_INPUT
    err = capsys.readouterr().err
    assert "DAMMRL_CONTROLLER_FIXED_PERIOD_S=-1: outside its range [0.01, 5]" in err
    assert err.count("\n") == 1


def test_sensor_list_prints_ports_or_says_none(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sensor", "list"]) == 0
    out = capsys.readouterr().out
    assert out.strip()


def test_sensor_emulate_serves_frames_on_its_link(tmp_path: Path) -> None:
    import subprocess
    import sys
    import time

    import serial

    from dammrl_core.intent.pad.protocol import FrameParser

    link = tmp_path / "ttyEMU"
    emulator = subprocess.Popen(
        [sys.executable, "-m", "dammrl.cli", "sensor", "emulate", "--link", str(link),
         "--seconds", "5"], stdout=subprocess.PIPE,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 10
        while not link.exists():
            assert time.monotonic() < deadline
            time.sleep(0.05)
        parser = FrameParser()
        with serial.Serial(str(link), timeout=0.5) as port:
            frames = []
            while len(frames) < 20 and time.monotonic() < deadline:
                frames += parser.feed(port.read(64))
        assert len(frames) >= 20 and not parser.errors
    finally:
        emulator.terminate()
        emulator.wait(10)


def test_lockstep_is_refused_with_a_person_at_the_sensor(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code = main(["up", "--mode", "semi-virtual", "--port", "/dev/null", "--lockstep"])
    assert code == Exit.USAGE
    assert "--lockstep is for simulation only" in capsys.readouterr().err


def test_lockstep_reaches_every_service() -> None:
    from dammrl.stack.launch import Stack
    from dammrl.stack.options import StackOptions
    from tests.busutil import free_port

    # a free port: a run of the user's own may hold the default one beside the tests
    stack = Stack(StackOptions(lockstep=True, port=free_port()))
    assert stack.environment()["DAMMRL_BUS_LOCKSTEP"] == "true"
    assert "DAMMRL_BUS_LOCKSTEP" not in Stack(StackOptions(port=free_port())).environment()


def test_a_port_in_time_wait_is_reused_and_a_held_port_is_a_clear_error() -> None:
    import socket

    from dammrl.stack.options import check_port
    from dammrl_core.errors import DammrlError

    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as Zenoh's listener (tokio)
    server.bind(("127.0.0.1", 0))
    server.listen()
    port = server.getsockname()[1]
    client = socket.create_connection(("127.0.0.1", port))
    accepted, _ = server.accept()
    with pytest.raises(DammrlError, match=rf"127.0.0.1:{port} .*held by python"):
        check_port(port)
    server.close()
    accepted.close()  # the side that closes first keeps the port in TIME_WAIT
    client.close()
    assert check_port(port) == port


IMPORTED_AT_EXIT = (
    "import atexit, runpy, sys\n"
    "atexit.register(lambda: print(' '.join(sorted(sys.modules)), file=sys.stderr))\n"
    "sys.argv = ['dammrl', *sys.argv[1:]]\n"
    "runpy.run_module('dammrl', run_name='__main__')\n"
)
HEAVY = ("torch", "mujoco", "pinocchio", "scipy", "numpy", "matplotlib", "ikpy", "mcap")


@pytest.mark.parametrize("command", ["stop", "status"])
def test_stop_and_status_import_the_bus_and_the_messages_only(command: str) -> None:
    """A stop must not wait for Python: ``dammrl stop`` (and ``status``) load neither the
    simulation, the learning nor the other commands (the whole CLI took 1.2 s of imports
    quiet and 85 s at load 40 before the arm heard the stop)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing there: the command runs to its end
    done = subprocess.run([sys.executable, "-c", IMPORTED_AT_EXIT, command, "--connect",
                           endpoint, *(["--timeout", "0.3"] if command == "stop" else [])],
                          capture_output=True, text=True, timeout=120, check=False)  # fmt: skip
    assert done.returncode == Exit.FAILED, done.stderr
    modules = set(done.stderr.splitlines()[-1].split())
    assert "zenoh" in modules and "schemas" in modules  # it did reach for the bus
    assert not {m.split(".")[0] for m in modules} & set(HEAVY)
    groups = {m for m in modules if m.startswith("dammrl.cli.")}
    assert groups <= {"dammrl.cli.common", f"dammrl.cli.{QUICK[command]}"}, groups


def test_every_command_help_ends_with_the_exit_codes() -> None:
    import argparse

    from dammrl.cli import parser
    from dammrl_core.errors import EXIT_CODES_HELP

    def commands(top: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
        found = []
        for action in top._actions:
            if isinstance(action, argparse._SubParsersAction):
                for command in action.choices.values():
                    found += [command, *commands(command)]
        return found

    every = commands(parser())
    assert len(every) > 15
    assert all(EXIT_CODES_HELP in (c.epilog or "") for c in every)


def test_every_option_and_argument_has_a_help_text() -> None:
    from dammrl.cli import parser

    missing = []

    def walk(node: argparse.ArgumentParser, path: str) -> None:
        for action in node._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{path} {name}")
            elif not action.help and not isinstance(action, argparse._HelpAction):
                missing.append(f"{path} {'/'.join(action.option_strings) or action.dest}")

    walk(parser(), "dammrl")
    assert not missing, missing


def test_version_and_shell_completion(capsys: pytest.CaptureFixture[str]) -> None:
    from dammrl import __version__

    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.strip() == f"dammrl {__version__}"
    with pytest.raises(SystemExit):
        main(["--print-completion", "bash"])
    script = capsys.readouterr().out
    assert "complete" in script and "frontier" in script and "--eval-seeds" in script


def test_a_missing_extra_is_a_one_line_error_before_any_work(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """Without foxglove-sdk or PyAV the command says which extra to install, no traceback,
    and a reach is not run for a video it cannot write."""
    import importlib.util

    real = importlib.util.find_spec

    def without_extras(name: str, *rest: object) -> object:
        return None if name in ("foxglove", "av") else real(name, *rest)  # type: ignore[arg-type]

    monkeypatch.setattr(importlib.util, "find_spec", without_extras)
    assert main(["view", "--port", "1"]) == Exit.USAGE
    assert "pip install 'dammrl[view]'" in capsys.readouterr().err
    assert main(["reach", "--video", str(tmp_path / "r.mp4")]) == Exit.USAGE
    err = capsys.readouterr()
    assert "pip install 'dammrl[video]'" in err.err and err.out == ""  # no reach ran
    assert main(["reach", "--video", str(tmp_path / "r.avi")]) == Exit.USAGE
    assert ".mp4 or .gif" in capsys.readouterr().err


def test_a_client_that_reaches_no_stack_says_so_within_seconds(tmp_path: Path) -> None:
    """echo, status and replay on a port nobody serves: one line naming the endpoint and
    what to check, not silence (a replay into the void would look like a success)."""
    from schemas import Header, TaskGoal, encode, key
    from services.recorder.core import McapRecorder
    from tests.busutil import free_port

    where = f"tcp/127.0.0.1:{free_port()}"
    echo = subprocess.run([sys.executable, "-m", "dammrl", "echo", "robot/state", "--connect",
                           where, "--duration", "6.5"], capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert f"dammrl: nothing answers at {where} (is `dammrl up` running" in echo.stderr
    assert echo.returncode == 1 and "Traceback" not in echo.stderr
    status = subprocess.run([sys.executable, "-m", "dammrl", "status", "--connect", where],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert status.returncode == 1 and f"nothing answers at {where}" in status.stdout
    recording = tmp_path / "one.mcap"
    recorder = McapRecorder(recording, "dammrl", {}, chunk_bytes=1 << 16)
    goal = TaskGoal(
        header=Header(stamp_ns=1, seq=0, source="sim"),
        episode=1,
        seed=0,
        start_m=(0.3, 0.0, -0.1),
        goal_m=(0.45, 0.0, -0.2),
        q_start_rad=(0.0,) * 6,
    )
    recorder.record(key("dammrl", TaskGoal, "sim"), encode(goal), 1)
    recorder.finish()
    replay = subprocess.run([sys.executable, "-m", "dammrl", "replay", str(recording),
                             "--connect", where], capture_output=True, text=True,
                            timeout=60)  # fmt: skip
    assert replay.returncode != 0 and f"nothing answers at {where}" in replay.stderr
    assert len(replay.stderr.strip().splitlines()) == 1, replay.stderr


def test_the_display_is_spelled_the_same_in_up_and_session_run(tmp_path: Path) -> None:
    """`up --display-port N` as `session run` spells it, `session run --display` as `up`
    does (it was "ambiguous"); both at once with --no-display is refused in one line."""
    from dammrl.cli import parser

    assert parser().parse_args(["up", "--display-port", "9000"]).display == 9000
    assert parser().parse_args(["up", "--display"]).display == 8080
    run = ["session", "run", "--participant", "P001", "--protocol", "event-vs-fixed"]
    assert parser().parse_args([*run, "--display"]).display is True
    done = subprocess.run([sys.executable, "-m", "dammrl", *run, "--root", str(tmp_path),
                           "--display", "--no-display"], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert done.returncode == 2
    assert done.stderr.strip() == "dammrl: error: --display and --no-display: give one of them"


def test_the_stop_console_joins_a_new_run_on_its_port_when_no_arm_heard_it(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session's next block is a new run on the same port, with new credentials: a stop
    console opened before could not reach it (no arm confirmed, the arm went on). It joins
    the run again and sends the stop once more."""
    import io

    from dammrl.cli import stop
    from dammrl.stack.stop import StopReport

    consoles: list[Console] = []

    class Console:
        def __init__(self, settings: object) -> None:
            self.closed, self.heard = False, bool(consoles)  # the first: the old run's
            consoles.append(self)

        def send(self, engaged: bool, reason: str, timeout_s: float) -> StopReport:
            return StopReport({"sim": 0.012} if self.heard else {}, [])

        def close(self) -> None:
            self.closed = True

    monkeypatch.setattr(stop, "StopConsole", Console)
    monkeypatch.setattr(stop, "bus_settings", lambda args: None)
    monkeypatch.setattr(sys, "stdin", io.StringIO("\n"))
    args = argparse.Namespace(console=True, release=False, reason="", timeout=0.1)
    assert stop._stop(args) == Exit.OK
    out, err = capsys.readouterr()
    assert "joining the run on the bus again" in err and "sim: stop confirmed after 12 ms" in out
    assert [c.closed for c in consoles] == [True, True]
