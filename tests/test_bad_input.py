"""Bad settings and files: one line naming what is wrong, a distinct exit code, no
traceback, never a value that cannot be a bound (``inf``, ``nan``).

Every ``DAMMRL_*`` variable of every settings class gets every bad value of ``BAD``; the
command-line paths (the ``dammrl`` tool and a service's entry point) are checked on a
sample of them.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator

import pytest
from pydantic import BaseModel

import dammrl.learning.rl.config
import services.common.config
import services.controller.config
import services.intent.config
import services.policy.config
import services.recorder.config
import services.robot.config
import services.sim.config
from dammrl.cli import main
from dammrl_core import human, models, task
from dammrl_core.arm.dynamixel.plugin import DynamixelSettings
from dammrl_core.arm.settings import ArmSettings
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.errors import ConfigurationError, Exit
from dammrl_core.intent.lsl import LslSettings
from dammrl_core.intent.pad.source import PadSettings
from dammrl_core.intent.simulated import SimulatedSettings
from dammrl_core.policy.settings import PolicySettings
from dammrl_core.robot import settings as robot
from dammrl_core.settings import Settings, variable
from dammrl_core.sim.settings import SimSettings

CLASSES: list[type[Settings]] = [
    services.common.config.BusSettings, ControllerSettings, services.intent.config.IntentSettings,
    PolicySettings, services.recorder.config.RecorderSettings, SimSettings,
    dammrl.learning.rl.config.TrainSettings, human.HumanModel, models.ModelSet, task.TaskSettings,
    robot.RobotSettings, ArmSettings, PadSettings, SimulatedSettings, DynamixelSettings,
    LslSettings,
]  # fmt: skip
BAD = ("abc", "inf", "-inf", "nan", "-1", "1e309", "[1,", "[1, 2]", '{"x": 1}', "", "\x7f")


def _variables(
    settings: type[BaseModel], prefix: tuple[str, ...] = ()
) -> Iterator[tuple[str, ...]]:
    """Every field's location, nested models' fields included."""
    for name, field in settings.model_fields.items():
        yield (*prefix, name)
        kind = field.annotation
        if isinstance(kind, type) and issubclass(kind, BaseModel):
            yield from _variables(kind, (*prefix, name))


CASES = [
    (cls, variable(cls, location), value)
    for cls in CLASSES
    for location in _variables(cls)
    for value in BAD
]


def test_every_settings_class_is_covered() -> None:
    assert set(CLASSES) >= set(_all_subclasses(Settings))


def _all_subclasses(cls: type) -> set[type]:
    return {sub for child in cls.__subclasses__() for sub in {child, *_all_subclasses(child)}}


@pytest.mark.parametrize(("cls", "name", "value"), CASES, ids=[f"{c[1]}={c[2]!r}" for c in CASES])
def test_a_bad_value_is_refused_in_one_line_naming_the_variable(
    monkeypatch: pytest.MonkeyPatch, cls: type[Settings], name: str, value: str
) -> None:
    monkeypatch.setenv(name, value)
    try:
        built = cls()
    except ConfigurationError as exc:
        message = str(exc)
        assert "\n" not in message and name.split("[")[0] in message, message
        return
    for number in _numbers(built):  # accepted: then it holds no infinite or NaN bound
        assert number == number and abs(number) != float("inf"), (name, value, number)


def _numbers(model: BaseModel) -> Iterator[float]:
    for value in model.model_dump().values():
        yield from _flatten(value)


def _flatten(value: object) -> Iterator[float]:
    if isinstance(value, float):
        yield value
    elif isinstance(value, list | tuple):
        for item in value:
            yield from _flatten(item)
    elif isinstance(value, dict):
        for item in value.values():
            yield from _flatten(item)


def test_a_misspelt_variable_is_refused_with_the_nearest_name(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("DAMMRL_CONTROLLER_KP_NM_PER_RAD", "[1, 1, 1, 1, 1, 1]")
    with pytest.raises(ConfigurationError, match="did you mean DAMMRL_CONTROLLER_KP\\?"):
        services.controller.config.ControllerSettings()


def test_a_variable_that_moved_to_a_plug_in_names_its_new_name(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from dammrl_core.arm.settings import ArmSettings
    from services.intent.config import IntentSettings

    monkeypatch.setenv("DAMMRL_ARM_PORT", "/dev/ttyUSB1")
    with pytest.raises(ConfigurationError, match="DAMMRL_ARM_PORT is now DAMMRL_DYNAMIXEL_PORT"):
        ArmSettings()
    monkeypatch.delenv("DAMMRL_ARM_PORT")
    monkeypatch.setenv("DAMMRL_INTENT_DECODER__ON_LEVEL", "0.3")
    with pytest.raises(ConfigurationError, match="is now DAMMRL_PAD_DECODER__ON_LEVEL"):
        IntentSettings()


def test_the_tool_exits_3_with_one_line_for_a_bad_setting(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    for name, value in (
        ("DAMMRL_CONTROLLER_KP", "[1, 2]"),
        ("DAMMRL_SIM_COMMAND_STALE_S", "inf"),
        ("DAMMRL_TASK_HOME_Q_RAD", "[0, 0]"),
        ("DAMMRL_MODELS_E_BIG_M", "x"),
    ):
        monkeypatch.setenv(name, value)
        assert main(["reach", "--seed", "1"]) == Exit.BAD_INPUT
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and name in err, err
        monkeypatch.delenv(name)


@pytest.mark.parametrize(
    ("service", "name", "value"),
    [("controller", "DAMMRL_CONTROLLER_KP", "[1, 2]"), ("sim", "DAMMRL_SIM_RANDOMIZATION", "{"),
     ("intent", "DAMMRL_INTENT_SOURCE", "nosuchsource"), ("policy", "DAMMRL_POLICY_KIND", "x"),
     ("recorder", "DAMMRL_BUS_CONNECT", "tcp/1.2.3.4:7447")],
)  # fmt: skip
def test_a_service_with_a_bad_setting_exits_3_with_one_line(
    service: str, name: str, value: str
) -> None:
    env = os.environ | {name: value}
    done = subprocess.run([sys.executable, "-m", f"services.{service}"], env=env,
                          capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert done.returncode == Exit.BAD_INPUT, done.stderr
    errors = [line for line in done.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and name in errors[0] and "Traceback" not in done.stderr, done.stderr
