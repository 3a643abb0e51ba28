"""The base of every ``DAMMRL_*`` settings class.

A bad value is one line naming its variable, what was expected and what was given
(never a traceback); numbers are finite (``inf`` or ``nan`` is no bound).
"""

from __future__ import annotations

import difflib
import json
import os
import re
from typing import Annotated, Any, ClassVar, TypeAlias

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict, SettingsError

from dammrl_core.errors import ConfigurationError

FINITE = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
"""The configuration of a plain settings model nested in a ``Settings`` class."""

_SHOWN_CHARS = 60

_NonNegative = Annotated[float, Field(ge=0)]
PerJoint: TypeAlias = tuple[float, float, float, float, float, float]
"""One value per joint, base to wrist (six, no fewer, no more)."""
PerJointNonNegative: TypeAlias = tuple[
    _NonNegative, _NonNegative, _NonNegative, _NonNegative, _NonNegative, _NonNegative
]
_Gain = Annotated[float, Field(ge=0, le=2000)]
_Damping = Annotated[float, Field(ge=0, le=200)]
PerJointGain: TypeAlias = tuple[_Gain, _Gain, _Gain, _Gain, _Gain, _Gain]
"""Joint stiffness, one per joint, 0-2000 N m/rad (the largest any arm side accepts)."""
PerJointDamping: TypeAlias = tuple[_Damping, _Damping, _Damping, _Damping, _Damping, _Damping]
"""Joint damping, one per joint, 0-200 N m s/rad."""


class Settings(BaseSettings):
    """Frozen, no unknown fields, finite numbers, nested fields as ``PREFIX_A__B``."""

    model_config: ClassVar[SettingsConfigDict] = SettingsConfigDict(
        frozen=True, extra="forbid", env_nested_delimiter="__", allow_inf_nan=False
    )

    def __init__(self, **values: Any) -> None:
        _refuse_unknown(type(self))
        try:
            super().__init__(**values)
        except SettingsError as exc:
            raise ConfigurationError(_unparsable(type(self), exc)) from None
        except ValidationError as exc:
            raise ConfigurationError(invalid_line(type(self), exc)) from None


MOVED: dict[str, tuple[str, frozenset[str], str]] = {
    "DAMMRL_ARM_": ("DAMMRL_DYNAMIXEL_", frozenset({"PORT", "BAUD", "CALIBRATION_FILE",
                    "WATCHDOG_S"}), "the Dynamixel driver's own settings"),
    "DAMMRL_INTENT_": ("DAMMRL_PAD_", frozenset({"PORT", "BAUD_RATE", "DECODER",
                       "CALIBRATION_FILE", "SENSOR_STALE_S", "RECONNECT_MAX_S"}),
                       "the pad's own settings"),
}  # fmt: skip
"""Fields that moved when the pad and the Dynamixel arm became plug-ins: old prefix ->
(new prefix, the fields, why)."""


def _refuse_unknown(settings: type[BaseSettings]) -> None:
    """A misspelt variable would silently leave its default in force (gains, limits):
    refuse it, with the nearest real name."""
    prefix = str(settings.model_config.get("env_prefix", "")).upper()
    fields = {name.upper() for name in settings.model_fields}
    for name in os.environ:
        upper = name.upper()
        if not prefix or not upper.startswith(prefix):
            continue
        field = upper[len(prefix) :].split("__", 1)[0]
        if field not in fields:
            new_prefix, moved, why = MOVED.get(prefix, ("", frozenset(), ""))
            if field in moved:
                raise ConfigurationError(f"{name} is now {new_prefix}{upper[len(prefix) :]} "
                                         f"({why})")  # fmt: skip
            starts = sorted((f for f in fields if field.startswith(f + "_")), key=len)
            near = starts[-1:] or difflib.get_close_matches(field, fields, n=1)
            hint = f"; did you mean {prefix}{near[0]}?" if near else ""
            raise ConfigurationError(f"unknown setting {name}{hint}")


def variable(settings: type[BaseSettings], location: tuple[int | str, ...]) -> str:
    """The environment variable of a field (``location`` as pydantic reports it)."""
    prefix = str(settings.model_config.get("env_prefix", ""))
    names = [str(part).upper() for part in location if isinstance(part, str)]
    indices = "".join(f"[{part}]" for part in location if isinstance(part, int))
    return prefix + "__".join(names) + indices


def invalid_line(settings: type[BaseSettings], exc: ValidationError) -> str:
    """Every error of ``exc`` on one line: ``VARIABLE=given: expected``."""
    parts = []
    for error in exc.errors(include_url=False):
        if not error["loc"]:  # a rule across fields: its message names them
            parts.append(_named(settings, str(error["msg"]).removeprefix("Value error, ")))
            continue
        given = _shown(error.get("input"))
        parts.append(f"{variable(settings, tuple(error['loc']))}={given}: {error['msg']}")
    return "invalid setting: " + "; ".join(parts)


def _named(settings: type[BaseSettings], message: str) -> str:
    """``message`` with each field name of ``settings`` as its environment variable."""
    for name in sorted(settings.model_fields, key=len, reverse=True):
        message = re.sub(rf"\b{name}\b", variable(settings, (name,)), message)
    return message


def error_line(exc: Exception) -> str:
    """Any error as one line; a settings error raised while building a larger model
    (pydantic wraps it) as its own message."""
    if not isinstance(exc, ValidationError):
        return " ".join(str(exc).split())
    parts = []
    for error in exc.errors(include_url=False):
        cause = error.get("ctx", {}).get("error")
        if isinstance(cause, ConfigurationError):
            parts.append(str(cause))
            continue
        message = str(error["msg"]).removeprefix("Value error, ")
        where = ".".join(map(str, error["loc"]))
        parts.append(f"{where}: {message}" if where else message)
    return "; ".join(parts)


def _unparsable(settings: type[BaseSettings], exc: SettingsError) -> str:
    """A list or nested value that is not JSON."""
    match = re.search(r'field "([^"]+)"', str(exc))
    name = variable(settings, (match.group(1),)) if match else str(exc)
    given = _environment(name)
    reason = f" ({exc.__cause__})" if exc.__cause__ else ""
    return (
        f"invalid setting: {name}={_shown(given)}: expected JSON, e.g. [1, 2] or "
        f'{{"key": 1}}{reason}'
    )


def _environment(name: str) -> str | None:
    wanted = name.upper()
    return next((v for k, v in os.environ.items() if k.upper() == wanted), None)


def _shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= _SHOWN_CHARS else text[: _SHOWN_CHARS - 3] + "..."


def environment_of(settings: BaseSettings) -> dict[str, str]:
    """The environment variables that give a service these settings: one per field set
    explicitly (``model_fields_set``), in the form the settings class reads back (strings
    as they are, everything else as JSON). A launcher builds typed settings objects,
    checked as it builds them, and hands their variables to the process it starts."""
    env = {}
    for name in sorted(settings.model_fields_set):
        value = getattr(settings, name)
        if value is None:  # not set: the service's own default, or its environment's
            continue
        if isinstance(value, os.PathLike):
            value = os.fspath(value)
        text = value if isinstance(value, str) else json.dumps(_plain(value))
        env[variable(type(settings), (name,))] = text
    return env


def _plain(value: Any) -> Any:
    """A settings value as JSON data (paths as strings, models as maps)."""
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value
