"""No limit switched off by a setting: every number of every settings class has a documented
range, and a value outside it (or a contradictory pair) is one line naming the variable,
the range and the value. The walk finds every ``Settings`` subclass by importing every
module, so a new setting without a range fails here."""

from __future__ import annotations

import importlib
import json
import os
import pkgutil
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import dammrl
import dammrl_core
import services
from dammrl_core.errors import ConfigurationError
from dammrl_core.settings import Range, Settings, number_fields

ROOT = Path(__file__).resolve().parent.parent


def _every_settings_class() -> list[type[Settings]]:
    for package in (dammrl_core, services, dammrl):
        for module in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            if not module.name.endswith("__main__"):
                importlib.import_module(module.name)
    found: set[type[Settings]] = set()
    todo = list(Settings.__subclasses__())
    while todo:
        cls = todo.pop()
        found.add(cls)
        todo += cls.__subclasses__()
    return sorted(found, key=lambda c: c.__name__)


CLASSES = _every_settings_class()


def test_the_walk_finds_the_settings_of_every_service_and_plug_in() -> None:
    names = {c.__name__ for c in CLASSES}
    assert {"ArmSettings", "SimSettings", "ControllerSettings", "TaskSettings", "BusSettings",
            "RecorderSettings", "PadSettings", "LslSettings", "DynamixelSettings",
            "ModelSet", "HumanModel", "PolicySettings", "TrainSettings"} <= names  # fmt: skip


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_every_number_has_both_bounds(cls: type[Settings]) -> None:
    unbounded = [name for name, bounds in number_fields(cls) if not bounds.bounded]
    assert not unbounded, f"give these a documented range (ge/gt and le/lt): {unbounded}"


def _outside(bounds: Range, integer: bool) -> Iterator[float]:
    """A value just below and one just above the range."""
    assert bounds.lower is not None and bounds.upper is not None
    step = 1 if integer else max(abs(bounds.lower), abs(bounds.upper), 1.0) * 1e-3
    yield bounds.lower if bounds.lower_open else bounds.lower - step
    yield bounds.upper if bounds.upper_open else bounds.upper + step


def _inside(bounds: Range, integer: bool) -> float:
    assert bounds.lower is not None and bounds.upper is not None
    middle = (bounds.lower + bounds.upper) / 2
    return round(middle) if integer else middle


def _cases() -> Iterator[tuple[type[Settings], str, Range]]:
    for cls in CLASSES:
        for variable, bounds in number_fields(cls):
            yield cls, variable, bounds


@pytest.mark.parametrize(
    ("cls", "variable", "bounds"), list(_cases()), ids=lambda v: v if isinstance(v, str) else ""
)
def test_a_value_outside_its_range_is_one_line_naming_variable_range_and_value(
    cls: type[Settings], variable: str, bounds: Range, monkeypatch: pytest.MonkeyPatch
) -> None:
    integer = _is_integer(cls, variable)
    for value in _outside(bounds, integer):
        environment = _environment(cls, variable, value, bounds, integer)
        with monkeypatch.context() as patch:
            for key, text in environment.items():
                patch.setenv(key, text)
            with pytest.raises(ConfigurationError) as refused:
                cls()
        line = str(refused.value)
        assert "\n" not in line
        shown = f"{value:g}" if isinstance(value, float) else str(value)
        assert f"{variable}=" in line, line
        assert f"outside its range {bounds}" in line, line
        assert shown in line or repr(value) in line, line


def _is_integer(cls: type[Settings], variable: str) -> bool:
    return _leaf_type(cls, variable) is int


def _path(cls: type[Settings], variable: str) -> list[str | int]:
    """The field path of ``variable`` (``PREFIX_A__B[2]`` -> ["a", "b", 2])."""
    prefix = str(cls.model_config.get("env_prefix", ""))
    rest = variable.removeprefix(prefix)
    index = None
    if rest.endswith("]"):
        rest, _, tail = rest.rpartition("[")
        index = tail.rstrip("]")
    path: list[str | int] = [part.lower() for part in rest.split("__")]
    if index is not None:
        path.append(0 if index == "i" else int(index))
    return path


def _leaf_type(cls: type[Settings], variable: str) -> Any:
    from dammrl_core.settings import _element, _unannotated, _without_none

    annotation: Any = cls
    for part in _path(cls, variable):
        current = _without_none(_unannotated(annotation)[0])
        if isinstance(part, str):
            annotation = current.model_fields[part].annotation
        else:
            annotation = _element(current, part)
    return _without_none(_unannotated(annotation)[0])


def _environment(
    cls: type[Settings], variable: str, value: float, bounds: Range, integer: bool
) -> dict[str, str]:
    """The environment that gives ``variable`` the ``value`` (a tuple element: the whole
    tuple, its other elements at their defaults or inside their ranges)."""
    path = _path(cls, variable)
    if not isinstance(path[-1], int):
        return {variable: json.dumps(value)}
    field_variable = variable.rpartition("[")[0]
    owner: Any = cls
    for part in path[:-2]:
        assert isinstance(part, str)
        owner = owner.model_fields[part].annotation
    default = owner.model_fields[path[-2]].get_default(call_default_factory=True)
    if default is None:
        count = len([n for n, _ in number_fields(cls) if n.startswith(field_variable + "[")])
        default = [_inside(bounds, integer)] * count
    elements = list(default)
    elements[int(path[-1])] = value
    return {field_variable: json.dumps(elements)}


def test_every_default_is_inside_its_range() -> None:
    for cls in CLASSES:
        cls()  # the defaults construct (ranges and cross checks hold)


# ---- the values the re-test found accepted ---------------------------------------------------
@pytest.mark.parametrize(
    ("variable", "value", "expected"),
    [
        ("DAMMRL_CONTROLLER_WORKSPACE_MIN_M", "[-1e6, -1e6, -1e6]",
         "DAMMRL_CONTROLLER_WORKSPACE_MIN_M[0]=-1000000.0: outside its range [0.05, 0.8]"),
        ("DAMMRL_ARM_TORQUE_FRACTION", "1e-9",
         "DAMMRL_ARM_TORQUE_FRACTION=1e-9: outside its range [0.3, 1]"),
        ("DAMMRL_ARM_STOP_KP_NM_PER_RAD", "[0, 0, 0, 0, 0, 0]",
         "DAMMRL_ARM_STOP_KP_NM_PER_RAD[0]=0: outside its range [5, 2000]"),
        ("DAMMRL_ARM_HOLD_KP_NM_PER_RAD", "[0, 0, 0, 0, 0, 0]",
         "DAMMRL_ARM_HOLD_KP_NM_PER_RAD[0]=0: outside its range [5, 2000]"),
        ("DAMMRL_SIM_HOLD_KP_NM_PER_RAD", "0",
         "DAMMRL_SIM_HOLD_KP_NM_PER_RAD=0: outside its range [5, 2000]"),
        ("DAMMRL_CONTROLLER_KP", "[0, 400, 200, 200, 50, 50]",
         "DAMMRL_CONTROLLER_KP[0]=0: outside its range [5, 2000]"),
        ("DAMMRL_ARM_SOFT_START_S", "0", "DAMMRL_ARM_SOFT_START_S=0: outside its range [0.2, 10]"),
        ("DAMMRL_ARM_MAX_RESTARTS", "0", "DAMMRL_ARM_MAX_RESTARTS=0: outside its range [1, 10]"),
        ("DAMMRL_TASK_TABLE_TOP_Z_M", "5",
         "DAMMRL_TASK_TABLE_TOP_Z_M=5: outside its range [-0.8, 0]"),
        ("DAMMRL_CONTROLLER_IK_ACCEPT_ERROR_M", "1",
         "DAMMRL_CONTROLLER_IK_ACCEPT_ERROR_M=1: outside its range (0, 0.01]"),
        ("DAMMRL_TASK_EPISODE_TIMEOUT_S", "1e9",
         "DAMMRL_TASK_EPISODE_TIMEOUT_S=1e9: outside its range [1, 3600]"),
    ],
)  # fmt: skip
def test_the_values_found_accepted_are_refused_naming_the_whole_range(
    variable: str, value: str, expected: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dammrl.cli.settings import settings_classes

    monkeypatch.setenv(variable, value)
    prefix = variable.split("_", 2)[:2]
    cls = next(c for c in settings_classes()
               if str(c.model_config.get("env_prefix")) == "_".join(prefix) + "_")  # fmt: skip
    with pytest.raises(ConfigurationError, match=re.escape(expected)):
        cls()


# ---- contradictory pairs --------------------------------------------------------------------
PAIRS = [
    ({"DAMMRL_CONTROLLER_WORKSPACE_MIN_M": "[0.1, -0.45, 0.5]"},
     "DAMMRL_CONTROLLER_WORKSPACE_MIN_M[2]=0.5: outside its range [-0.8, 0.2) (below "
     "DAMMRL_CONTROLLER_WORKSPACE_MAX_M[2]=0.2)"),
    ({"DAMMRL_TASK_START_MIN_M": "[0.5, -0.15, -0.1]"},
     "DAMMRL_TASK_START_MIN_M[0]=0.5: outside its range [0.05, 0.38]"),
    ({"DAMMRL_TASK_GOAL_MIN_XY_M": "[0.7, -0.15]"},
     "DAMMRL_TASK_GOAL_MIN_XY_M[0]=0.7: outside its range [0.05, 0.6]"),
    ({"DAMMRL_TASK_REACH_DISTANCE_M": "[0.5, 0.3]"},
     "DAMMRL_TASK_REACH_DISTANCE_M[0]=0.5: outside its range (0, 0.3]"),
    ({"DAMMRL_ARM_SPEED_FRACTION": "0.95", "DAMMRL_ARM_OVERSPEED_STOP_FRACTION": "0.9"},
     "DAMMRL_ARM_SPEED_FRACTION=0.95: outside its range (0, 0.9)"),
    ({"DAMMRL_ARM_MAX_KP_NM_PER_RAD": "100"},
     "DAMMRL_ARM_HOLD_KP_NM_PER_RAD[0]=300: outside its range [5, 100]"),
    ({"DAMMRL_ARM_COMMAND_STALE_S": "0.02", "DAMMRL_ARM_LOOP_RATE_HZ": "50"},
     "DAMMRL_ARM_COMMAND_STALE_S=0.02: outside its range [0.04, 1]"),
    ({"DAMMRL_SIM_HOLD_KP_NM_PER_RAD": "500", "DAMMRL_SIM_MAX_KP_NM_PER_RAD": "400"},
     "DAMMRL_SIM_HOLD_KP_NM_PER_RAD=500: outside its range [5, 400]"),
    ({"DAMMRL_SIM_SPEED_GOVERNOR_FRACTION": "0.8"},
     "DAMMRL_SIM_REFERENCE_SPEED_FRACTION=0.9: outside its range (0, 0.8]"),
    ({"DAMMRL_MODELS_E_SMALL_M": "0.02"},
     "DAMMRL_MODELS_E_SMALL_M=0.02: outside its range (0, 0.01)"),
    ({"DAMMRL_MODELS_STEP_SMALL_M": "[0.05, 0.01, 0.01]"},
     "DAMMRL_MODELS_STEP_SMALL_M[0]=0.05: outside its range (0, 0.03]"),
    ({"DAMMRL_PAD_DECODER__OFF_LEVEL": "0.3"},
     "DAMMRL_PAD_DECODER__OFF_LEVEL=0.3: outside its range (0, 0.15)"),
    ({"DAMMRL_LSL_DECODER__MIN_CONTRACTION_S": "0.8"},
     "DAMMRL_LSL_DECODER__MIN_CONTRACTION_S=0.8: outside its range [0, 0.5)"),
]  # fmt: skip


@pytest.mark.parametrize(("environment", "expected"), PAIRS)
def test_a_contradictory_pair_is_refused_naming_the_range_the_other_leaves(
    environment: dict[str, str], expected: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dammrl.cli.settings import settings_classes

    for key, value in environment.items():
        monkeypatch.setenv(key, value)
    prefix = next(iter(environment)).rsplit("_", 1)[0]
    refused = []
    for cls in settings_classes():
        if prefix.startswith(str(cls.model_config.get("env_prefix", "")).rstrip("_")):
            try:
                cls()
            except ConfigurationError as exc:
                refused.append(str(exc))
    assert any(expected in line for line in refused), refused


def test_the_workspace_floor_must_keep_the_fingertip_above_the_table(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from dammrl.stack.runner import ReachSettings
    from dammrl_core.control.settings import ControllerSettings, check_workspace
    from dammrl_core.task import TaskSettings

    monkeypatch.setenv("DAMMRL_TASK_TABLE_TOP_Z_M", "-0.1")  # the table raised 15 cm
    with pytest.raises(
        ConfigurationError,
        match=re.escape(
            "DAMMRL_CONTROLLER_WORKSPACE_MIN_M[2]=-0.235: outside its range [-0.088, 0.8]"
        ),
    ):
        check_workspace(ControllerSettings(), TaskSettings())
    with pytest.raises(ValueError, match="keeps the fingertip above the table"):
        ReachSettings()  # every in-process composition (pydantic wraps the error)


def test_torque_limits_that_cannot_hold_the_arm_are_refused_for_that_arm() -> None:
    from dammrl_core.arm.settings import holds_its_weight
    from dammrl_core.robot import RobotSettings

    robot = RobotSettings().load()
    limits = (robot.q_min, robot.q_max)
    holds_its_weight(robot, limits, 0.3)  # the lowest the range allows holds this arm
    light = robot.__class__(**{**vars(robot), "tau_max": robot.tau_max / 2})
    with pytest.raises(ConfigurationError, match=r"DAMMRL_ARM_TORQUE_FRACTION=0\.3: outside "
                       r"its range \[0\.51, 1\] for this arm \(shoulder_pitch"):  # fmt: skip
        holds_its_weight(light, limits, 0.3)


# ---- as a user meets it ----------------------------------------------------------------------
def _run(*argv: str, **environment: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ) | {"PYTHONPATH": str(ROOT)} | environment
    return subprocess.run([sys.executable, *argv], capture_output=True, text=True, timeout=120,
                          env=env, cwd=ROOT, stdin=subprocess.DEVNULL, check=False)  # fmt: skip


@pytest.mark.slow
def test_dammrl_up_refuses_a_switched_off_workspace_before_anything_starts() -> None:
    done = _run("-m", "dammrl", "up", "--episodes", "1", "--bus-port", "1",
                DAMMRL_CONTROLLER_WORKSPACE_MIN_M="[-1e6, -1e6, -1e6]")  # fmt: skip
    assert done.returncode == 3, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "outside its range [0.05, 0.8]" in lines[0], done.stderr


@pytest.mark.slow
def test_a_service_refuses_a_zero_stiffness_hold_in_one_line_with_exit_3() -> None:
    done = _run("-m", "services.sim", DAMMRL_SIM_HOLD_KP_NM_PER_RAD="0",
                DAMMRL_LOG_LEVEL="ERROR")  # fmt: skip
    assert done.returncode == 3, done
    assert "DAMMRL_SIM_HOLD_KP_NM_PER_RAD=0: outside its range [5, 2000]" in done.stderr
    assert "Traceback" not in done.stderr


def test_the_settings_reference_is_generated_from_the_classes() -> None:
    """docs/reference/settings-ranges.md is `dammrl settings --markdown`: a new setting or
    range changes it (regenerate it with that command)."""
    from dammrl.cli.settings import markdown

    page = ROOT / "docs" / "reference" / "settings-ranges.md"
    assert page.read_text() == markdown(), "regenerate: dammrl settings --markdown > " + str(page)


def test_the_registry_lists_every_settings_class() -> None:
    from dammrl.cli.settings import settings_classes

    assert set(settings_classes()) == set(CLASSES)
