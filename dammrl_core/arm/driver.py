"""The real arm's drives behind one interface, and the registry of their plug-ins.

A ``Driver`` connects to an arm's drives, reads its joints, writes the joint law
tau = tau_ff + kp (q_ref - q) + kd (dq_ref - dq) (each backend realises it as its drives
allow), and disconnects; a context manager, in the style of LeRobot's ``Robot``. A
``DriverPlugin`` is what a package registers under the entry-point group
``dammrl.arm_drivers``: its name, its own settings class (with an environment prefix of
its own), how to make a driver from them, and its tools (scan the bus, calibrate the arm).
Choosing a backend is a setting (``DAMMRL_ARM_DRIVER``), never an edit of dammrl.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol, cast

import numpy as np
from pydantic import BaseModel

from dammrl_core import plugins
from dammrl_core.errors import DammrlError
from dammrl_core.robot import RobotDescription
from dammrl_core.settings import Settings

ENTRY_POINTS = "dammrl.arm_drivers"


class DriverError(DammrlError):
    """The drives' bus failed: a timeout, a corrupt answer, a missing drive."""


class BadReplyError(DriverError):
    """A drive's answer that cannot be the one asked for: the wrong length (a late answer
    to an earlier request), or a value no drive reports. A missed read, as a timeout is."""


class PortLostError(DriverError):
    """The device itself failed (a USB adapter pulled out): it must be reopened."""


@dataclass(frozen=True)
class DriveFault:
    """A drive that latched a fault and cut (or may have cut) its torque."""

    joint: int  # 0-based
    what: str  # e.g. "servo 6: overload"
    restartable: bool  # a restart clears it (an overload); else the drive stays off


@dataclass(frozen=True)
class JointState:
    q_rad: np.ndarray  # (6,)
    dq_rad_s: np.ndarray  # (6,)
    tau_nm: np.ndarray  # (6,)
    faults: tuple[DriveFault, ...] = ()
    button_travel_m: float = 0.0
    restarting: frozenset[int] = frozenset()
    """Joints whose drive restarts (silent, no torque): their values are the last read."""


@dataclass(frozen=True)
class DriveCommand:
    """The joint law to realise (joint frame, SI) and the torque limit per joint."""

    q_ref: np.ndarray
    dq_ref: np.ndarray
    tau_ff: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    torque_limit_nm: np.ndarray


HoldLaw = Callable[[JointState], DriveCommand]
"""The law drives hold with from their torque-on, made from the state read just before."""


class Driver(Protocol):
    @property
    def stall_s(self) -> float | None:
        """The host's silence after which the drives stop themselves (None: never)."""
        ...

    def connect(self, torque: bool = True, hold: HoldLaw | None = None) -> bool:
        """Open and power up: ``torque``, the drives hold with ``hold``'s law from the moment
        their torque goes on (None: zero gains, the caller writes a law at once; a host
        that stalls then leaves the arm limp), those that already hold keep theirs; else
        the torque goes off, for moving the arm by hand. True when any drive already held
        (a reconnection: no soft start, which would soften the joints held); raises
        DriverError."""
        ...

    def read_state(self) -> JointState: ...

    def write_command(self, command: DriveCommand) -> None: ...

    def torque_off(self) -> list[int]:
        """Every drive that answers lets go (the arm falls: only with a support); the
        drives that did not confirm it."""
        ...

    def rearm(self) -> list[int]:
        """After the host was silent longer than ``stall_s``: the drives that had stopped
        themselves, made to obey again (they hold where they are)."""
        ...

    def restart(self, joint: int) -> None:
        """Clear a restartable fault of ``joint``'s drive; returns at once. The drive is
        left out of reads and writes until it is back, then holds where its joint is."""
        ...

    def joint_limits(self, robot: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
        """This arm's joint limits (q_min, q_max) [rad] from its calibration, inside
        ``robot``'s (the URDF's, where the calibration has none)."""
        ...

    def disconnect(self) -> None: ...

    def __enter__(self) -> Driver: ...

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 trace: TracebackType | None) -> None: ...  # fmt: skip


class DriverPlugin(Protocol):
    """An arm driver as a package provides it (entry point group ``dammrl.arm_drivers``)."""

    name: str
    settings: type[Settings]
    """Its own settings (port, calibration file, ...), with an environment prefix of its own."""

    def create(self, settings: Settings) -> Driver: ...

    def scan(self, settings: Settings) -> list[str]:
        """The devices on the bus, one line each (``dammrl robot scan``)."""
        ...

    def calibrate(self, settings: Settings, robot: RobotDescription, limits: bool,
                  ask: Callable[[str], None], say: Callable[[str], None]) -> BaseModel:  # fmt: skip
        """Guided calibration with the arm moved by hand; the result, saved as JSON, is the
        driver's calibration file (``dammrl robot calibrate``)."""
        ...


BUILT_IN: dict[str, str] = {"dynamixel": "dammrl_core.arm.dynamixel.plugin:PLUGIN"}


def driver_plugins() -> dict[str, str]:
    """Every installed arm driver's name and who provides it."""
    return plugins.origins(ENTRY_POINTS, BUILT_IN)


def driver_plugin(name: str) -> DriverPlugin:
    """The arm driver plug-in called ``name``."""
    what = "arm driver (DAMMRL_ARM_DRIVER)"
    return cast(DriverPlugin, plugins.load(ENTRY_POINTS, BUILT_IN, name, what))
