"""What a run of the stack is (``StackOptions``: the mode, the person's input, the arm,
the recording), which services it starts with which settings, and every check made before
anything starts: a setting, a file, a device or a port that cannot be used is one line
now, never a dead service later."""

from __future__ import annotations

import contextlib
import importlib
import os
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from pydantic_settings import BaseSettings

from dammrl_core.arm.settings import ArmSettings
from dammrl_core.coadaptation import Targets
from dammrl_core.control.settings import ControllerSettings, check_workspace
from dammrl_core.errors import (
    DammrlError,
    UsageError,
)
from dammrl_core.policy.settings import PolicySettings
from dammrl_core.settings import environment_of
from dammrl_core.task import TaskSettings
from services.common.config import BusSettings
from services.intent.config import IntentSettings
from services.recorder.config import RecorderSettings

MODES = {
    "virtual": ("sim", "policy", "intent", "controller"),
    "semi-virtual": ("sim", "policy", "intent", "controller"),  # intent reads the sensor
    "real": ("robot", "policy", "intent", "controller"),  # the arm on a servo bus
}


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
    first_reach_held_by: str = ""  # the first reach waits for this one's resume ("": none)


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
                                       first_reach_held_by=o.first_reach_held_by,
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
