"""The Dynamixel arm as a driver plug-in: its settings (``DAMMRL_DYNAMIXEL_``), its driver, its
tools. dammrl's own plug-in is registered as a built-in; a package's is found through its
entry point (``dammrl.arm_drivers``) and looks the same."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.arm.dynamixel.calibration import Calibration, load_calibration
from dammrl_core.arm.dynamixel.driver import DynamixelDriver
from dammrl_core.arm.dynamixel.tools import MODEL_NAMES, guided_calibration, scan
from dammrl_core.robot import RobotDescription
from dammrl_core.settings import Settings

_Id = Annotated[int, Field(ge=0, le=252)]
_Gear = Annotated[float, Field(ge=0.1, le=1000)]
_TorqueConstant = Annotated[float, Field(gt=0, le=1000)]


class DynamixelSettings(Settings):
    """The servo bus and the arm's calibration (environment prefix ``DAMMRL_DYNAMIXEL_``)."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_DYNAMIXEL_")

    port: str = Field("/dev/ttyUSB0", min_length=1)
    """The servo bus's serial device (a U2D2 or another USB adapter)."""
    baud: int = Field(1_000_000, ge=9600, le=10_500_000)
    """The bus's baud rate [bit/s] (the servos' range: 9600 bit/s - 10.5 Mbit/s)."""
    calibration_file: Path | None = None
    """From ``dammrl robot calibrate``; None: the default calibration (the emulated arm)."""
    watchdog_s: float = Field(0.1, ge=0.02, le=2.54)
    """The servos stop by themselves when the bus is silent this long [s]."""

    ids: tuple[_Id, _Id, _Id, _Id, _Id, _Id] | None = None
    """Servo ids, base first, for a calibration to come (else the calibration file's)."""
    gear_ratios: tuple[_Gear, _Gear, _Gear, _Gear, _Gear, _Gear] | None = None
    """Servo turns per joint turn, base first, for a calibration to come."""
    torque_per_amp_nm: (
        tuple[
            _TorqueConstant,
            _TorqueConstant,
            _TorqueConstant,
            _TorqueConstant,
            _TorqueConstant,
            _TorqueConstant,
        ]
        | None
    ) = None
    """Servo output torque per ampere [N m/A], base first, for a calibration to come."""
    button_id: int | None = Field(None, ge=-1, le=252)
    """The goal button's board on the bus (-1: none), for a calibration to come."""

    def calibration(self) -> Calibration:
        """The arm's calibration: the file's (or the default), and for a calibration to
        come, the ids, gears, torque constants and button given here."""
        base = (
            Calibration()
            if self.calibration_file is None
            else load_calibration(self.calibration_file)
        )
        given = {"ids": self.ids, "gear_ratios": self.gear_ratios,
                 "torque_per_amp_nm": self.torque_per_amp_nm}  # fmt: skip
        update: dict[str, object] = {k: v for k, v in given.items() if v is not None}
        if self.button_id is not None:
            update["button_id"] = None if self.button_id < 0 else self.button_id
        return Calibration.model_validate(base.model_dump() | update) if update else base


class DynamixelPlugin:
    name = "dynamixel"
    settings = DynamixelSettings

    def create(self, settings: Settings) -> DynamixelDriver:
        assert isinstance(settings, DynamixelSettings)
        return DynamixelDriver(settings.port, settings.calibration(), settings.baud,
                               settings.watchdog_s)  # fmt: skip

    def scan(self, settings: Settings) -> list[str]:
        assert isinstance(settings, DynamixelSettings)
        return [
            f"id {d.servo_id:3d}  {MODEL_NAMES.get(d.model, f'model {d.model}')}  "
            f"firmware {d.firmware}"
            for d in scan(settings.port, settings.baud)
        ]

    def calibrate(
        self,
        settings: Settings,
        robot: RobotDescription,
        limits: bool,
        ask: Callable[[str], None],
        say: Callable[[str], None],
    ) -> Calibration:
        assert isinstance(settings, DynamixelSettings)
        return guided_calibration(settings.port, settings.calibration(), robot, limits, ask, say)


PLUGIN = DynamixelPlugin()
