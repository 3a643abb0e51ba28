"""``dammrl up``: start the services of a mode as child processes and watch them.

The launcher opens its own Zenoh session (a router) listening on a loopback endpoint;
every service connects to it (and, as Zenoh peers, to each other). It waits for each service's
liveliness token, prints each EpisodeResult, and stops every child on Ctrl-C / SIGTERM,
when the requested episodes are done, or (exit 1) when a service dies on its own.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from pydantic_settings import BaseSettings
from zenoh.handlers import RingChannel

from dammrl.stack.stop import StopConsole
from dammrl_core.arm.settings import ArmSettings
from dammrl_core.coadaptation import Targets
from dammrl_core.control.settings import ControllerSettings, check_workspace
from dammrl_core.errors import (
    ConfigurationError,
    DammrlError,
    Exit,
    JobFailedError,
    UsageError,
)
from dammrl_core.policy.settings import PolicySettings
from dammrl_core.settings import environment_of
from dammrl_core.task import TaskSettings
from schemas import (
    DecisionRequest,
    DecodeError,
    EpisodeResult,
    Health,
    Intent,
    Message,
    ModelChoice,
    RobotState,
    decode,
    key,
)
from services.common.bus import SESSION_CLOSE_WAIT_S, close_within, zenoh_config
from services.common.certificates import create_credentials
from services.common.config import BusSettings
from services.common.runs import RunCard, remove_card, write_card
from services.common.runtime import SignalStop, stopping_on_signals
from services.common.security import OPERATOR, claim_run_credentials, run_credentials
from services.intent.config import IntentSettings
from services.recorder.config import RecorderSettings

MODES = {
    "virtual": ("sim", "policy", "intent", "controller"),
    "semi-virtual": ("sim", "policy", "intent", "controller"),  # intent reads the sensor
    "real": ("robot", "policy", "intent", "controller"),  # the arm on a servo bus
}
START_TIMEOUT_S = 60.0
EMULATOR_START_S = START_TIMEOUT_S
"""The emulated arm's pty appears this soon (it imports MuJoCo as a service does: 15 s
was too short beside two CPU hogs) [s]."""
FIRST_STATE_S = 30.0
"""The arm publishes its first state this soon after every service is alive [s]."""
QUIET_S = 30.0
"""Without an episode result this long, ``dammrl up`` says what each service reports [s]."""
STOP_TIMEOUT_S = 5.0
ARM_SERVICES = ("sim", "robot")
MAX_RESTARTS = 5
"""How often ``dammrl up`` restarts a recorder that died before it gives up."""


@dataclass(frozen=True)
class StackOptions:
    mode: str = "virtual"
    episodes: int | None = None
    seed: int = 0
    model: tuple[int, int] | None = None  # a fixed M_ij; None: the learned policy
    trigger: str = "event"
    port: int = 7447
    namespace: str = "dammrl"
    json: bool = False
    record: Path | None = None  # also run the recorder into this MCAP file
    study: str = ""  # the session the recording belongs to (JSON, into its metadata)
    prior: tuple[float, float] | None = None  # the person's carried human-model posterior
    checkpoint: Path | None = None  # a policy refined for the person (None: the settings')
    adaptive: Targets | None = None  # the adaptive policy with these targets (None: not)
    pad_port: str | None = None  # the pressure pad's serial device (semi-virtual, or real)
    lsl_stream: str | None = None  # a wearable sensor's LSL stream (semi-virtual, or real)
    intent: str | None = None  # the intent source (default: pad with pad_port, lsl with a stream)
    calibration: Path | None = None  # the person's: `dammrl sensor|intent calibrate`
    lockstep: bool = False  # every service on the robot clock (DAMMRL_BUS_LOCKSTEP); sim only
    credentials: Path | None = None  # from `dammrl bus init`: mutual TLS and the ACL
    insecure: bool = False  # plain tcp on loopback instead of this run's own credentials
    robot_port: str | None = None  # real: the arm driver's port setting
    robot_calibration: Path | None = None  # real: the arm driver's calibration file
    emulate_robot: bool = False  # real: serve the emulated (Dynamixel) arm at robot_port first
    outcome_hold_s: float = 0.0  # a reach's outcome stays this long before the next goal [s]


def check_port(port: int) -> int:
    """``port`` if the stack can listen there on loopback, else a clear error naming what
    holds it. Probed as Zenoh binds (SO_REUSEADDR), so a port left in TIME_WAIT by the
    previous run is free; the stack never moves to another port behind the user's back
    (tools that connect to it by default would never meet it)."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
            sock.listen()
        except OSError as exc:
            holder = port_holder(port)
            raise DammrlError(
                f"cannot listen on 127.0.0.1:{port} ({exc.strerror}): held by {holder}; "
                "stop it or choose another --bus-port"
            ) from exc
    return port


def port_holder(port: int) -> str:
    """Which process listens on TCP ``port`` (from /proc on Linux), or 'another process'."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(OSError):
            for line in Path(table).read_text().splitlines()[1:]:
                fields = line.split()
                if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == port:
                    inodes.add(fields[9])  # state 0A: LISTEN
    sockets = {f"socket:[{inode}]" for inode in inodes}
    for fd_dir in Path("/proc").glob("[0-9]*/fd") if sockets else ():
        with contextlib.suppress(OSError):  # a process that ended, or not ours to read
            if any(_link(fd) in sockets for fd in fd_dir.iterdir()):
                name = (fd_dir.parent / "comm").read_text().strip()
                return f"{name} (pid {fd_dir.parent.name})"
    return "another process"


def _link(path: Path) -> str:
    """Where a /proc fd points ('' once it is gone)."""
    try:
        return os.readlink(path)
    except OSError:
        return ""


def check_options(options: StackOptions) -> None:
    """Refuse options that cannot run, before anything starts."""
    if options.mode not in MODES:
        raise DammrlError(f"mode {options.mode!r} is not available; choose from {sorted(MODES)}")
    if options.mode == "semi-virtual" and options.lockstep:
        raise UsageError(
            "--lockstep is for simulation only: in semi-virtual mode a person at the sensor "
            "needs real time"
        )
    if options.mode == "semi-virtual" and not _a_person(options):
        raise UsageError("semi-virtual mode needs a person: --port (the pressure pad's serial "
                         "device), --stream (a wearable's LSL stream) or DAMMRL_INTENT_SOURCE "
                         "naming a sensor's source")  # fmt: skip
    needs = {"pad": ("--port", options.pad_port), "lsl": ("--stream", options.lsl_stream)}
    if options.intent in needs and not needs[options.intent][1]:
        raise UsageError(f"--intent {options.intent} needs {needs[options.intent][0]}")
    given = [name for name, (_, value) in needs.items() if value]
    if options.intent is not None and given and given != [options.intent]:
        raise UsageError(f"--intent {options.intent} with {needs[given[0]][0]}: one source")
    if options.pad_port and options.lsl_stream:
        raise UsageError("--port (the pad) and --stream (a wearable) are two people: one of them")
    if options.lsl_stream and options.calibration is None:
        raise UsageError("--stream needs --calibration: the person's file from "
                         "`dammrl intent calibrate --stream NAME --out FILE`")  # fmt: skip
    if options.mode == "real" and options.lockstep:
        raise UsageError("--lockstep is for simulation only: a real arm runs in real time")
    if options.emulate_robot and not options.robot_port:
        raise UsageError("--emulate-robot needs --robot-port (where the emulated bus appears)")
    if options.emulate_robot and ArmSettings().driver != "dynamixel":
        raise UsageError("--emulate-robot emulates a Dynamixel chain: DAMMRL_ARM_DRIVER must be "
                         "dynamixel")  # fmt: skip
    if options.mode != "real" and (options.robot_port or options.emulate_robot):
        raise UsageError("--robot-port and --emulate-robot are for --mode real")
    if options.record is not None:
        check_record(options.record)
    _check_calibration(options)


def check_record(record: Path) -> None:
    """A recording to make: its name ends in .mcap, its folder exists and may be written,
    and neither it nor a continuation of it (``NAME-001.mcap``, ...) exists: checked before
    anything starts, never created or overwritten behind the user's back."""
    if record.suffix != ".mcap":
        raise UsageError(f"--record {record}: the file name must end in .mcap")
    folder = record.parent
    if not folder.is_dir():
        raise UsageError(f"--record {record}: no folder {folder} (make it first)")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"--record {record}: cannot write in {folder} (permission denied)")
    existing = [p for p in recording_files(record) if p.exists()]
    if existing:
        raise UsageError(f"--record {record}: {existing[0]} exists: choose another name "
                         "(nothing is overwritten, and a restarted recorder continues in "
                         "NAME-001.mcap, ...)")  # fmt: skip


def _check_calibration(options: StackOptions) -> None:
    """A person's calibration file that cannot be used: a clear error now, not a dead
    service."""
    if options.calibration is None:
        return
    if options.lsl_stream:
        from dammrl_core.intent.emg.calibration import load_calibration as load_wearable

        load_wearable(options.calibration)
        return
    from dammrl_core.intent.pad.calibration import load_calibration
    from dammrl_core.intent.pad.decoder import PressDecoder
    from dammrl_core.intent.pad.source import PadSettings

    PressDecoder(load_calibration(options.calibration), PadSettings().decoder)


def _a_person(options: StackOptions) -> bool:
    """Someone decides: the pad, a wearable, or the environment's non-simulated source."""
    named = options.intent or IntentSettings().source
    return bool(options.pad_port or options.lsl_stream) or named != "simulated"


def recording_files(record: Path) -> list[Path]:
    """The recorder's files of ``record``: itself, then its rotations and continuations
    after a restart (``NAME-001.mcap``, ...), in the order they were written."""
    return [record, *sorted(record.parent.glob(f"{record.stem}-[0-9][0-9][0-9].mcap"))]


def cut_recordings(record: Path) -> list[Path]:
    """The recorder's files of ``record`` that a death cut."""
    from services.recorder.core import complete_mcap

    return [f for f in recording_files(record) if f.exists() and not complete_mcap(f)]


def check_settings(services: tuple[str, ...], env: dict[str, str]) -> None:
    """Build every settings class the services will read, from the environment they will
    get (the intent source's and the arm driver's own included): a bad value is one line
    naming its variable now, before anything starts."""
    from dammrl_core.arm.driver import driver_plugin
    from dammrl_core.intent.source import source_plugin
    from services.intent.config import IntentSettings

    with _environment(env):
        BusSettings()
        for name in services:
            for settings in importlib.import_module(f"services.{name}.config").SETTINGS:
                settings()
        if "intent" in services:
            source_plugin(IntentSettings().source).settings()
        if "robot" in services:
            driver_plugin(ArmSettings().driver).settings()
        if "controller" in services:
            check_workspace(ControllerSettings(), TaskSettings())


@contextlib.contextmanager
def _environment(env: dict[str, str]) -> Iterator[None]:
    saved = dict(os.environ)
    os.environ.clear()
    os.environ.update(env)
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


def _die_with_parent() -> None:
    """In the child: receive SIGHUP when the launcher dies, even by kill -9 (Linux), so that
    a service can tell its launcher's death from a stop (SIGTERM) and remove the run's
    keys. Ignored until the child's own handler is set (an ignored signal stays ignored
    across exec): a launcher dying while the child starts is then noticed by the child's
    check of its parent, not by a death without a clean end."""
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGHUP)  # PR_SET_PDEATHSIG


def check_stack(options: StackOptions) -> None:
    """Everything ``Stack`` checks before it starts a service, but its port: a session
    checks each block's run so, before anyone is enrolled."""
    check_options(options)
    env = dict(os.environ)
    for settings in [BusSettings(namespace=options.namespace), *run_settings(options)]:
        env.update(environment_of(settings))
    check_settings(services_of(options), env)


def services_of(options: StackOptions) -> tuple[str, ...]:
    """The services a run of ``options`` starts, the recorder first (it sees everything)."""
    recorder = ("recorder",) if options.record is not None else ()
    return recorder + MODES[options.mode]


def run_settings(o: StackOptions) -> list[BaseSettings]:
    """What a run of ``o`` sets for its services (but the bus), from the command line."""
    task = TaskSettings(seed=o.seed, episodes=o.episodes)
    settings: list[BaseSettings] = [task]
    chosen = {} if o.model is None else {"human_model": o.model[0], "robot_model": o.model[1]}
    settings.append(ControllerSettings(trigger=o.trigger, outcome_hold_s=o.outcome_hold_s,
                                       **chosen))  # type: ignore[arg-type]  # fmt: skip
    if o.model is not None:
        settings.append(PolicySettings(kind="fixed", **chosen))  # type: ignore[arg-type]
    if o.prior is not None:
        settings.append(PolicySettings(prior=o.prior))
    if o.checkpoint is not None:
        settings.append(PolicySettings(checkpoint=o.checkpoint.resolve()))
    if o.adaptive is not None:
        settings.append(PolicySettings(kind="adaptive", targets=o.adaptive))
    settings += _intent_settings(o) + _arm_settings(o)
    if o.record is not None:
        settings.append(RecorderSettings(out=o.record, mode=o.mode, study=o.study))
    return settings


def _intent_settings(o: StackOptions) -> list[BaseSettings]:
    """The pad when its port is given, a wearable when its stream is (semi-virtual, or
    real with a person at it)."""
    from dammrl_core.intent.lsl import LslSettings
    from dammrl_core.intent.pad.source import PadSettings

    calibration = {} if o.calibration is None else {"calibration_file": o.calibration.resolve()}
    if o.lsl_stream is not None:
        wearable = LslSettings(stream=o.lsl_stream, **calibration)  # type: ignore[arg-type]
        return [IntentSettings(source="lsl"), wearable]
    if o.pad_port is None:
        return [] if o.intent is None else [IntentSettings(source=o.intent)]
    pad = PadSettings(port=o.pad_port, **calibration)  # type: ignore[arg-type]
    return [IntentSettings(source="pad"), pad]


def _arm_settings(o: StackOptions) -> list[BaseSettings]:
    """The arm driver's port and calibration, when given (real mode)."""
    from dammrl_core.arm.driver import driver_plugin

    if o.mode != "real":
        return []
    plugin = driver_plugin(ArmSettings().driver)
    given = {"port": o.robot_port}
    if o.robot_calibration is not None:
        given["calibration_file"] = str(o.robot_calibration.resolve())
    missing = [k for k, v in given.items() if v and k not in plugin.settings.model_fields]
    if missing:
        raise UsageError(f"the arm driver {plugin.name!r} has no {', '.join(missing)} "
                         "setting: give its settings in its environment")  # fmt: skip
    return [plugin.settings(**{k: v for k, v in given.items() if v})]


class Stack:
    def __init__(
        self,
        options: StackOptions,
        out: Callable[[str], None] = print,
        info: Callable[[str], None] = print,
        on_result: Callable[[EpisodeResult], None] | None = None,
        on_up: Callable[[zenoh.Session], None] | None = None,
    ) -> None:
        """``out`` receives the episode results, ``info`` the progress lines; ``on_result``
        each episode's result as it is counted (a session's trial log keeps it at once);
        ``on_up`` the stack's hub session once every service is alive: the operator's
        (the launcher's role; a participant display joins with its own, :meth:`join`)."""
        check_options(options)
        self.options = options
        self.out = out
        self.info = info
        port = check_port(options.port)
        self.own_credentials = options.credentials is None and not options.insecure
        self.credentials = run_credentials(port) if self.own_credentials else options.credentials
        scheme = "tcp" if self.credentials is None else "tls"
        self.endpoint = f"{scheme}/127.0.0.1:{port}"
        self.children: dict[str, subprocess.Popen[bytes]] = {}
        self.emulator: subprocess.Popen[bytes] | None = None
        self.results: list[EpisodeResult] = []
        self.on_result = on_result
        self.on_up = on_up
        self.finishing = threading.Event()  # finish(): end the run after the current result
        self.prompts: PatientPrompts | None = None
        self.recorder_restarts = 0
        self.ignored = 0  # messages on task/result that were not an episode's result
        self.joined: list[zenoh.Session] = []  # sessions of other roles (join), closed at the end
        check_settings(self.services(), self.environment())
        self.progress: Progress | None = None

    def environment(self) -> dict[str, str]:
        """The children's environment: this one, and the variables of the settings the run
        gives them (built typed, checked as they are built)."""
        env = dict(os.environ)
        for settings in self.service_settings():
            env.update(environment_of(settings))
        env.setdefault("DAMMRL_LOG_LEVEL", "WARNING")  # progress comes from the launcher
        return env

    def service_settings(self) -> list[BaseSettings]:
        """What this run sets for its services, from the command line."""
        o = self.options
        credentials = None if self.credentials is None else self.credentials.resolve()
        # lockstep only when asked: otherwise the environment's
        lockstep: dict[str, Any] = {"lockstep": True} if o.lockstep else {}
        bus = BusSettings(connect=[self.endpoint], namespace=o.namespace, launcher_pid=os.getpid(),
                          credentials=credentials, **lockstep)  # fmt: skip
        return [bus, *run_settings(o)]

    def run(self) -> int:
        """Run until done; the exit code of ``dammrl up``."""
        # a router: it brokers for the services until their direct peer links are up, so a
        # recorder misses nothing a service publishes in its first milliseconds
        settings = BusSettings(
            listen=[self.endpoint],
            namespace=self.options.namespace,
            mode="router",
            credentials=self.credentials,
        )
        if self.own_credentials:  # this run's own: a peer without them cannot join
            assert self.credentials is not None
            shutil.rmtree(self.credentials, ignore_errors=True)
            create_credentials(self.credentials)
            claim_run_credentials(self.credentials)  # its services remove it if we die
        write_card(self.card())  # the tools and emulators beside it find it
        with stopping_on_signals() as stop:
            # the services' hub, and the operator's session (a session's console, a stop)
            session = zenoh.open(zenoh_config(settings, OPERATOR, rate_limits=True))
            try:
                results = session.declare_subscriber(key(self.options.namespace, EpisodeResult))
                if self.options.pad_port is not None and not self.options.json:
                    self.prompts = PatientPrompts(session, self.options.namespace, self.info)
                self._start_children(session, stop)
                self._wait_alive(session, stop)
                if self.on_up is not None:
                    self.on_up(session)
                self.progress = Progress(session, self.options.namespace, self.info)
                return self._watch(results, stop)
            finally:
                self._stop_children()
                for joined in self.joined:
                    close_within(joined, SESSION_CLOSE_WAIT_S)
                close_within(session, SESSION_CLOSE_WAIT_S)  # a vanished peer can hold it
                remove_card(self.options.port, os.getpid())
                if self.own_credentials and self.credentials is not None:
                    shutil.rmtree(self.credentials, ignore_errors=True)

    def card(self) -> RunCard:
        """What a tool needs to join this run: where, how, and the person's input."""
        o = self.options
        credentials = None if self.credentials is None else str(self.credentials.resolve())
        pad = None if o.pad_port is None else os.path.abspath(o.pad_port)
        return RunCard(pid=os.getpid(), port=o.port, endpoint=self.endpoint, namespace=o.namespace,
                       credentials=credentials, pad_port=pad, lsl_stream=o.lsl_stream)  # fmt: skip

    def join(self, role: str) -> zenoh.Session:
        """A session of this process on the run's bus with ``role``'s certificate (the
        participant's display: its comfort rating and nothing else), closed with the run."""
        settings = BusSettings(connect=[self.endpoint], namespace=self.options.namespace,
                               credentials=self.credentials, role=role)  # fmt: skip
        session = zenoh.open(zenoh_config(settings, role))
        self.joined.append(session)
        return session

    def stop_console(self) -> StopConsole:
        """The operator's stop on the run's bus, its session opened now: a stop typed
        later costs no start-up and is repeated until every arm confirms it."""
        return StopConsole(BusSettings(connect=[self.endpoint], namespace=self.options.namespace,
                                       credentials=self.credentials))  # fmt: skip

    def finish(self) -> None:
        """End the run before its last episode (a session ends a block early)."""
        self.finishing.set()

    def services(self) -> tuple[str, ...]:
        return services_of(self.options)

    def _start_children(self, session: zenoh.Session, stop: SignalStop) -> None:
        env = self.environment()
        if self.options.emulate_robot:
            self._start_emulator(env)
        for name in self.services():
            self.children[name] = self._spawn(name, env)
            if name == "recorder":  # record from the first message of the stack on
                self._wait_alive(session, stop, quiet=True)
        self.info(f"started {', '.join(self.children)} on {self.endpoint}")

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

    def inspect_commands(self) -> str:
        """What to type in another terminal to look at this run (clients find its
        credentials and namespace from the port; alone on this machine, they find it
        without one)."""
        at = f"--bus-port {self.options.port}"
        commands = (f"status {at}", f"echo robot/state {at}", f"view {at}")
        lines = [f"  dammrl {command}" for command in commands]
        return "\n".join(["inspect it from another terminal:", *lines,
                          f"stop the arm: dammrl stop {at}"])  # fmt: skip

    def _wait_alive(self, session: zenoh.Session, stop: SignalStop, quiet: bool = False) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        wanted, alive = set(self.children), set[str]()
        while time.monotonic() < deadline and not stop.is_set():
            self._check_children()
            replies = session.liveliness().get(f"{self.options.namespace}/alive/*", timeout=1.0)
            alive = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}
            if wanted <= alive:
                if not quiet:
                    self.info(f"all services alive: {', '.join(sorted(wanted))}")
                    self.info(self.inspect_commands())
                return
            time.sleep(0.2)
        if not stop.is_set():
            missing = ", ".join(sorted(wanted - alive))
            raise JobFailedError(
                f"services not alive after {START_TIMEOUT_S:.0f} s: {missing} (their logs say why)"
            )

    def _watch(
        self, results: zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]], stop: SignalStop
    ) -> int:
        total = self.options.episodes
        while not stop.is_set():
            if self.finishing.is_set():
                self.info(summary(self.results))
                return self._verdict()
            self._check_children()
            if self.prompts is not None:
                self.prompts.show()
            if self.progress is not None:
                self.progress.check()
            sample = results.try_recv()
            if sample is None:
                time.sleep(0.02)
                continue
            result = self._accept(sample.payload.to_bytes())
            if result is None:
                continue
            if self.progress is not None:
                self.progress.advanced()
            self.results.append(result)
            if self.on_result is not None:
                self.on_result(result)
            self._report(result)
            self._say_if_undecided(result)
            if total is not None and len(self.results) >= total:
                self.info(summary(self.results))
                return self._verdict()
        self.info(f"stopping on signal {stop.signum}")
        if (verdict := self._verdict()) != Exit.OK:
            return verdict
        return Exit.OK if total is None else Exit.INTERRUPTED  # open-ended: a signal ends it

    def _say_if_undecided(self, result: EpisodeResult) -> None:
        """An episode that ended without a single decision could not be done: say at once
        whose input never answered, and what to check."""
        if undecided(result):
            self.info(f"episode {result.episode} could not be done: in {result.t_total_s:.0f} s "
                      f"no decision came from {self.input_of_the_person()}")  # fmt: skip

    def _verdict(self) -> int:
        """Exit FAILED when the person's input never joined: episodes ended without a
        decision and no episode of the run had one (one line says so)."""
        lacking = [r for r in self.results if undecided(r)]
        if not lacking or any(r.n_decisions > 0 for r in self.results):
            return Exit.OK
        self.info(f"dammrl: {len(lacking)} of {len(self.results)} episodes could not be done: "
                  f"no decision ever came from {self.input_of_the_person()}")  # fmt: skip
        return Exit.FAILED

    def input_of_the_person(self) -> str:
        """Whose decisions the run waits for, and how that input joins this run."""
        o, port = self.options, self.options.port
        if o.pad_port is not None:
            return (f"the pad at {o.pad_port} (is someone pressing it? an emulated patient "
                    f"joins by itself: `dammrl sensor emulate --link {o.pad_port} --pattern "
                    f"patient`, or give it --bus-port {port})")  # fmt: skip
        if o.lsl_stream is not None:
            return (f"the wearable's stream {o.lsl_stream!r} (is the person moving? an "
                    "emulated armband joins by itself: `dammrl intent emulate --stream "
                    f"{o.lsl_stream} --pattern patient`, or --bus-port {port})")  # fmt: skip
        named = o.intent or IntentSettings().source
        return f"the intent source {named!r} (what does `dammrl status --bus-port {port}` say?)"

    def _accept(self, payload: bytes) -> EpisodeResult | None:
        """An episode result to count, or None (logged): undecodable, not from the
        controller (on a secured bus the ACL already drops those), or an episode already
        counted (a replay)."""
        try:
            result = decode(EpisodeResult, payload)
        except DecodeError as exc:
            self._ignored(f"a message on task/result: {exc}")
            return None
        counted = {r.episode for r in self.results}
        if result.header.source != "controller" or result.episode in counted:
            why = "a repeat" if result.episode in counted else f"from {result.header.source!r}"
            self._ignored(f"an episode result ({why})")
            return None
        return result

    def _ignored(self, what: str) -> None:
        """Say the first few, then every 1000th (a flood must not flood the terminal)."""
        self.ignored += 1
        if self.ignored <= 3 or self.ignored % 1000 == 0:
            self.info(f"ignored {what} ({self.ignored} so far)")

    def _report(self, result: EpisodeResult) -> None:
        if self.options.json:
            self.out(json.dumps(result_dict(result)))
            return
        total = self.options.episodes or "?"
        self.out(
            f"episode {result.episode}/{total}: {result.outcome} in {result.t_total_s:.1f} s, "
            f"N_osc {result.n_osc}, final error {result.final_error_m * 1000:.1f} mm"
            + ("" if result.success else f" ({result.reason})")
        )

    @staticmethod
    def _spawn(name: str, env: dict[str, str]) -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            [sys.executable, "-m", f"services.{name}"],
            env=env,
            preexec_fn=_die_with_parent,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # Ctrl-C reaches the launcher only; it stops them
        )

    def _check_children(self) -> None:
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

    def _stop_children(self) -> None:
        self._stop_processes(list(self.children.values()))
        if self.emulator is not None:  # last: the robot service leaves the arm holding
            self._stop_processes([self.emulator])

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


SWITCH = "adaptive: after reach"
"""How the policy's Health detail begins after a switch (services.policy.node)."""


class Progress:
    """``dammrl up`` never waits silently: the arm's first state must come within
    ``FIRST_STATE_S`` of the services being alive (else the run fails, with what the
    services' Health says), and every ``QUIET_S`` without an episode result prints what
    each service reports."""

    def __init__(self, session: zenoh.Session, namespace: str, out: Callable[[str], None]):
        self.out = out
        self.health: dict[str, Health] = {}
        self.first_state = False
        self.since = time.monotonic()
        self.said = self.since
        self.stopped: dict[str, bool] = {}
        self.switch = ""  # the adaptive policy's last switch said
        self._healths = session.declare_subscriber(f"{namespace}/health/*", RingChannel(256))
        self._states = session.declare_subscriber(key(namespace, RobotState), RingChannel(1))

    def _take(self) -> None:
        """What arrived (rings filled by Zenoh without Python: a flood costs nothing here)."""
        while (sample := self._healths.try_recv()) is not None:
            with contextlib.suppress(DecodeError):
                health = decode(Health, sample.payload.to_bytes())
                self.health[health.service] = health
        if not self.first_state and self._states.try_recv() is not None:
            self.first_state = True
            self._states.undeclare()  # type: ignore[no-untyped-call]

    def advanced(self) -> None:
        self.since = self.said = time.monotonic()

    def check(self) -> None:
        self._take()
        self._say_stops()
        self._say_switch()
        now = time.monotonic()
        if not self.first_state and now - self.since > FIRST_STATE_S:
            raise JobFailedError(
                f"no robot state {FIRST_STATE_S:.0f} s after the start: {self.report()}"
            )
        if now - self.said > QUIET_S:
            self.said = now
            self.out(f"no episode ended for {now - self.since:.0f} s: {self.report()}")

    def _say_stops(self) -> None:
        """An arm that stops (an emergency stop, a fault) is said at once, once."""
        arms = [h for h in self.health.values() if h.service in ARM_SERVICES]
        for health in arms:
            stopped = health.state == "stopped"
            if stopped and not self.stopped.get(health.service):
                reason = health.detail.split(";")[0]
                self.out(f"{health.service} stopped: {reason} (it holds; Ctrl-C ends the run)")
            self.stopped[health.service] = stopped

    def _say_switch(self) -> None:
        """The adaptive policy re-selected its models (S3): said once, with its reason."""
        policy = self.health.get("policy")
        if policy is not None and policy.detail.startswith(SWITCH) and policy.detail != self.switch:
            self.switch = policy.detail
            self.out(f"policy {policy.detail}")

    def report(self) -> str:
        """What each service's last Health says, on one line."""
        healths = sorted(self.health.values(), key=lambda h: h.service)
        if not healths:
            return "no service reported its health"
        return "; ".join(
            f"{h.service} {h.state}" + (f" ({h.detail})" if h.detail else "") for h in healths
        )


class PatientPrompts:
    """Semi-virtual: tell the person at the pad when the arm waits for them, where the goal
    is, what their press was read as, and which sub-model the policy thinks they follow."""

    def __init__(self, session: zenoh.Session, namespace: str, out: Callable[[str], None]):
        self.out = out
        self.subscribers = [
            (t, session.declare_subscriber(key(namespace, t)))
            for t in (DecisionRequest, ModelChoice, Intent)
        ]
        self.estimate = ""
        self.prompted = -1

    def show(self) -> None:
        for message_type, subscriber in self.subscribers:
            while (sample := subscriber.try_recv()) is not None:
                with contextlib.suppress(DecodeError):  # the services count bad messages
                    self._say(decode(message_type, sample.payload.to_bytes()))

    def _say(self, message: Message) -> None:
        if isinstance(message, ModelChoice) and message.posterior and message.request >= 0:
            p_small = message.posterior[1]
            likely, p = ("E_small", p_small) if p_small >= 0.5 else ("E_big", 1 - p_small)
            self.estimate = f"  [policy: you decide like {likely}, p {p:.2f}]"
        elif isinstance(message, DecisionRequest) and message.request != self.prompted:
            self.prompted = message.request  # a re-sent request is not a new prompt
            axis = "xyz"[message.primary_axis]
            ahead_mm = (
                message.goal_m[message.primary_axis] - message.ee_pos_m[message.primary_axis]
            ) * 1000
            where = f"{abs(ahead_mm):.0f} mm {'ahead' if ahead_mm >= 0 else 'behind'} on {axis}"
            self.out(f"  request {message.request}: press now - the goal is {where} "
                     "(firm = forward, light = back)")  # fmt: skip
        elif isinstance(message, Intent) and message.person:
            direction = "+1 forward" if message.u_h > 0 else "-1 back"
            radius = "quick -> E_big" if message.human_model == 1 else "held -> E_small"
            self.out(f"  read {direction}, {radius}, after {message.decision_s:.2f} s"
                     f"{self.estimate}")  # fmt: skip


def undecided(result: EpisodeResult) -> bool:
    """An episode that timed out without any decision: the person's input could not do it.
    A hold ends a reach for the arm's or the controller's reason (its own line says which),
    however early: not the person's input, so not blamed on it."""
    return result.n_decisions == 0 and result.outcome == "timeout"


def result_dict(result: EpisodeResult) -> dict[str, object]:
    """The JSON object of one episode: the keys of ``dammrl reach --json``."""
    fields = result.model_dump(mode="json", exclude={"header", "episode"})
    return fields | {"episode": result.episode}


def summary(results: list[EpisodeResult]) -> str:
    n = len(results)
    if n == 0:
        return "no episode ended"
    wins = sum(r.success for r in results)
    mean_t = sum(r.t_total_s for r in results) / n
    mean_osc = sum(r.n_osc for r in results) / n
    return (
        f"{wins}/{n} successful ({wins / n:.0%}), mean time {mean_t:.1f} s, "
        f"mean N_osc {mean_osc:.1f}"
    )
