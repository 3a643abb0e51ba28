"""`dammrl echo` started before the run it listens to: a `dammrl up` started after it
speaks TLS with credentials of its own, which did not exist when echo began."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.busutil import Lines, free_port, wait_for

pytestmark = pytest.mark.slow  # a whole stack, real time


def test_echo_started_before_the_run_finds_it() -> None:
    """echo stayed on plain tcp, never connected, and said nothing more."""
    port = free_port()
    echo = subprocess.Popen([sys.executable, "-m", "dammrl", "echo", "robot/state", "--connect",
                             f"tcp/127.0.0.1:{port}", "--count", "3", "--duration", "150"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    said, printed = Lines(echo.stderr), Lines(echo.stdout)  # each read on a thread of its own
    up = None
    try:
        said.wait_for("nothing answers", 30)  # alone first, and says so
        up = subprocess.Popen([sys.executable, "-m", "dammrl", "up", "--bus-port", str(port),
                               "--episodes", "1"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)  # fmt: skip
        echo.wait(150)  # not communicate(): it would race the threads for the pipes' lines
        up.wait(120)  # its one episode, then it stops its services
    finally:
        for process in (echo, up):  # SIGTERM: the launcher stops its services too
            if process is not None and process.poll() is None:
                process.terminate()
                process.wait(30)
    assert echo.returncode == 0, said.lines
    said.wait_for("a run answers at tls/127.0.0.1", 10)  # the pipes' ends read on threads

    def states() -> int:
        return sum('"key": "dammrl/robot/state"' in line for line in list(printed.lines))

    wait_for(lambda: states() >= 3, 10, "echo's three states")
    assert states() == 3
