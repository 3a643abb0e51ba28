"""The services of a run as child processes: started (the recorder first, and the
emulated arm before the robot service), watched (a service that exits is an error; a
recorder that dies is restarted into a new file), and stopped (SIGTERM, then kill)."""

from __future__ import annotations

import ctypes
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from dammrl.stack.options import StackOptions, cut_recordings, services_of
from dammrl_core.errors import (
    ConfigurationError,
    Exit,
    JobFailedError,
)
from services.common.runtime import SignalStop

START_TIMEOUT_S = 60.0
EMULATOR_START_S = START_TIMEOUT_S
"""The emulated arm's pty appears this soon (it imports MuJoCo as a service does: 15 s
was too short beside two CPU hogs) [s]."""
STOP_TIMEOUT_S = 5.0
MAX_RESTARTS = 5
"""How often ``dammrl up`` restarts a recorder that died before it gives up."""


class ServiceProcesses:
    """The run's services as child processes, and the emulated arm when asked."""

    def __init__(self, options: StackOptions, environment: Callable[[], dict[str, str]],
                 info: Callable[[str], None]) -> None:  # fmt: skip
        """``environment`` gives the children's environment (read again at a restart)."""
        self.options = options
        self.environment = environment
        self.info = info
        self.children: dict[str, subprocess.Popen[bytes]] = {}
        self.emulator: subprocess.Popen[bytes] | None = None
        self.recorder_restarts = 0

    def start(self, session: zenoh.Session, stop: SignalStop) -> None:
        """Every service of the run; the recorder first, alive before the others start, so
        that it records from the stack's first message on."""
        env = self.environment()
        if self.options.emulate_robot:
            self._start_emulator(env)
        for name in services_of(self.options):
            self.children[name] = self._spawn(name, env)
            if name == "recorder":
                self.wait_alive(session, stop)

    def _start_emulator(self, env: dict[str, str]) -> None:
        """The emulated arm, served at the robot port before the robot service opens it."""
        port = Path(str(self.options.robot_port))
        port.unlink(missing_ok=True)
        command = [sys.executable, "-m", "dammrl", "robot", "emulate", "--port", str(port),
                   "--follow-goals"]  # fmt: skip
        if self.options.robot_calibration is not None:
            command += ["--calibration", str(self.options.robot_calibration.resolve())]
        self.emulator = subprocess.Popen(
            command, env=env, preexec_fn=_die_with_parent, stdin=subprocess.DEVNULL,
            start_new_session=True,
        )  # fmt: skip
        deadline = time.monotonic() + EMULATOR_START_S
        while not port.exists():
            if self.emulator.poll() is not None or time.monotonic() > deadline:
                raise JobFailedError(f"the emulated arm did not come up at {port}")
            time.sleep(0.05)
        self.info(f"emulated arm at {port}")

    def wait_alive(self, session: zenoh.Session, stop: SignalStop) -> bool:
        """Until every started service's liveliness token is on the bus (True), or a signal
        (False); a service that exits or stays silent for ``START_TIMEOUT_S`` is an error."""
        deadline = time.monotonic() + START_TIMEOUT_S
        wanted, alive = set(self.children), set[str]()
        while time.monotonic() < deadline and not stop.is_set():
            self.check()
            replies = session.liveliness().get(f"{self.options.namespace}/alive/*", timeout=1.0)
            alive = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}
            if wanted <= alive:
                return True
            time.sleep(0.2)
        if stop.is_set():
            return False
        missing = ", ".join(sorted(wanted - alive))
        raise JobFailedError(
            f"services not alive after {START_TIMEOUT_S:.0f} s: {missing} (their logs say why)"
        )

    def check(self) -> None:
        """A service that exited is an error (a bad setting: its own exit code); the
        recorder alone is restarted, up to ``MAX_RESTARTS`` times."""
        for name, child in self.children.items():
            code = child.poll()
            if code == Exit.BAD_INPUT:
                raise ConfigurationError(f"service {name} cannot start (its log says why)")
            if code is not None and name == "recorder" and self.recorder_restarts < MAX_RESTARTS:
                self._restart_recorder(code)
            elif code is not None:
                raise JobFailedError(f"service {name} exited unexpectedly with code {code}")

    def _restart_recorder(self, code: int) -> None:
        """The session must not depend on its logger: complete the file the recorder was
        cut off in, and start it again into a new file (the stack goes on meanwhile)."""
        from dammrl.stack.recording import repair_in_place

        self.recorder_restarts += 1
        assert self.options.record is not None
        repaired = [repair_in_place(p) for p in cut_recordings(self.options.record)]
        self.children["recorder"] = self._spawn("recorder", self.environment())
        saved = "".join(f"; {r['to']} completed ({r['messages']} messages)" for r in repaired)
        self.info(f"the recorder exited with code {code}: restarted into a new file "
                  f"({self.recorder_restarts} of {MAX_RESTARTS} restarts){saved}")  # fmt: skip

    def stop(self) -> None:
        """Every service, then the emulated arm (last: the robot service leaves it holding)."""
        self._stop_processes(list(self.children.values()))
        if self.emulator is not None:
            self._stop_processes([self.emulator])

    @staticmethod
    def _spawn(name: str, env: dict[str, str]) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [sys.executable, "-m", f"services.{name}"],
            env=env,
            preexec_fn=_die_with_parent,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # Ctrl-C reaches the launcher only; it stops them
        )

    @staticmethod
    def _stop_processes(children: list[subprocess.Popen[bytes]]) -> None:
        for child in children:
            if child.poll() is None:
                child.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for child in children:
            try:
                child.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def _die_with_parent() -> None:
    """In the child: receive SIGHUP when the launcher dies, even by kill -9 (Linux), so that
    a service can tell its launcher's death from a stop (SIGTERM) and remove the run's
    keys. Ignored until the child's own handler is set (an ignored signal stays ignored
    across exec): a launcher dying while the child starts is then noticed by the child's
    check of its parent, not by a death without a clean end."""
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGHUP)  # PR_SET_PDEATHSIG
