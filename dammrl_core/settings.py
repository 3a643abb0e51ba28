"""The base of every ``DAMMRL_*`` settings class.

A bad value is one line naming its variable, what was expected and what was given
(never a traceback); numbers are finite (``inf`` or ``nan`` is no bound). Every number
has a documented range (both bounds: a limit must not be switched off by a large or tiny
value, ``tests/test_settings_ranges.py``), and a value outside it is refused naming the
range, e.g. ``DAMMRL_ARM_TORQUE_FRACTION=1e-9: outside its range [0.3, 1]``.
"""

from __future__ import annotations

import difflib
import inspect
import json
import os
import re
import types
import typing
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, TypeAlias

import annotated_types
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, SettingsConfigDict, SettingsError

from dammrl_core.errors import ConfigurationError

FINITE = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, use_attribute_docstrings=True)
"""The configuration of a plain settings model nested in a ``Settings`` class."""

_SHOWN_CHARS = 60

_Angle = Annotated[float, Field(ge=-3.2, le=3.2)]
PerJoint: TypeAlias = tuple[_Angle, _Angle, _Angle, _Angle, _Angle, _Angle]
"""One joint angle per joint, base to wrist (six, no fewer, no more), -3.2-3.2 rad."""
_Armature = Annotated[float, Field(ge=0, le=1)]
PerJointArmature: TypeAlias = tuple[_Armature, _Armature, _Armature, _Armature, _Armature,
                                    _Armature]  # fmt: skip
"""Reflected rotor inertia, one per joint, 0-1 kg m^2."""
MIN_STIFFNESS_NM_PER_RAD = 5.0
"""A hold, stop or command softer than this is no hold: a wrist with the reference arm's
0.26 N m of gravity would sag 0.05 rad on it, a shoulder's 10 % model error 0.27 rad."""
MIN_DAMPING_NMS_PER_RAD = 0.5
"""Less damping lets a hold ring: about half the critical damping of the reference arm's
wrist at the stop stiffness."""
_Gain = Annotated[float, Field(ge=MIN_STIFFNESS_NM_PER_RAD, le=2000)]
_Damping = Annotated[float, Field(ge=MIN_DAMPING_NMS_PER_RAD, le=200)]
PerJointGain: TypeAlias = tuple[_Gain, _Gain, _Gain, _Gain, _Gain, _Gain]
"""Joint stiffness, one per joint, 5-2000 N m/rad (the largest any arm side accepts)."""
PerJointDamping: TypeAlias = tuple[_Damping, _Damping, _Damping, _Damping, _Damping, _Damping]
"""Joint damping, one per joint, 0.5-200 N m s/rad."""


class Settings(BaseSettings):
    """Frozen, no unknown fields, finite numbers, nested fields as ``PREFIX_A__B``."""

    model_config: ClassVar[SettingsConfigDict] = SettingsConfigDict(
        frozen=True, extra="forbid", env_nested_delimiter="__", allow_inf_nan=False,
        use_attribute_docstrings=True,
    )  # fmt: skip

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


BOUND_ERRORS = ("greater_than", "greater_than_equal", "less_than", "less_than_equal")
"""pydantic's error types of a number beyond one of its bounds."""


def invalid_line(settings: type[BaseSettings], exc: ValidationError) -> str:
    """Every error of ``exc`` on one line: ``VARIABLE=given: expected``; a number beyond a
    bound with its whole range."""
    parts = []
    for error in exc.errors(include_url=False):
        location = tuple(error["loc"])
        nested = _model_at(settings, location)
        if nested is not None and error["type"] == "value_error":  # a rule across fields
            message = str(error["msg"]).removeprefix("Value error, ")
            parts.append(_named(settings, message, nested, location))
            continue
        given = _shown(error.get("input"))
        expected = str(error["msg"])
        bounds = field_range(settings, location) if error["type"] in BOUND_ERRORS else None
        if bounds is not None:
            expected = f"outside its range {bounds}"
        parts.append(f"{variable(settings, location)}={given}: {expected}")
    return "invalid setting: " + "; ".join(parts)


# ---- documented ranges ------------------------------------------------------------------
@dataclass(frozen=True)
class Range:
    """A number's documented range; each bound closed (``[``, ``]``) or open (None: none)."""

    lower: float | None = None
    upper: float | None = None
    lower_open: bool = False
    upper_open: bool = False

    def __str__(self) -> str:
        lower = "-inf" if self.lower is None else _number(self.lower)
        upper = "inf" if self.upper is None else _number(self.upper)
        opening = "(" if self.lower_open or self.lower is None else "["
        closing = ")" if self.upper_open or self.upper is None else "]"
        return f"{opening}{lower}, {upper}{closing}"

    @property
    def bounded(self) -> bool:
        """Both bounds are documented."""
        return self.lower is not None and self.upper is not None


def _number(value: float) -> str:
    return f"{value:,}" if isinstance(value, int) and abs(value) >= 10_000 else f"{value:g}"


def range_of(metadata: Iterable[object]) -> Range:
    """The range that pydantic metadata (``Field(ge=..., lt=...)``) declares."""
    bounds: dict[str, Any] = {}
    for item in metadata:
        if isinstance(item, FieldInfo):
            inner = range_of(item.metadata)
            bounds |= {k: v for k, v in vars(inner).items() if v is not None and v is not False}
        elif isinstance(item, annotated_types.Ge | annotated_types.Gt):
            bounds["lower"] = item.ge if isinstance(item, annotated_types.Ge) else item.gt
            bounds["lower_open"] = isinstance(item, annotated_types.Gt)
        elif isinstance(item, annotated_types.Le | annotated_types.Lt):
            bounds["upper"] = item.le if isinstance(item, annotated_types.Le) else item.lt
            bounds["upper_open"] = isinstance(item, annotated_types.Lt)
    return Range(**bounds)


def field_range(model: type[BaseModel], location: tuple[int | str, ...]) -> Range | None:
    """The documented range of the number at ``location`` (as pydantic reports an error:
    field names, nested models' fields, tuple indices) in ``model``; None: not a number."""
    annotation: Any = model
    metadata: list[object] = []
    for part in location:
        current = _without_none(annotation)
        if isinstance(part, str):
            if not (inspect.isclass(current) and issubclass(current, BaseModel)):
                continue  # a union member's tag (pydantic names the type it tried)
            if part not in current.model_fields:
                return None
            info = current.model_fields[part]
            annotation, metadata = info.annotation, list(info.metadata)
        else:
            annotation, metadata = _element(current, part), []
        annotation, extra = _unannotated(annotation)
        metadata += extra
    if _without_none(annotation) not in (int, float):
        return None
    return range_of(metadata)


def number_fields(model: type[BaseModel], prefix: str | None = None) -> list[tuple[str, Range]]:
    """Every number a settings class reads (nested models' and tuples' elements too), as
    (environment variable, documented range)."""
    if prefix is None:
        prefix = str(model.model_config.get("env_prefix", ""))
    found = []
    for name, info in model.model_fields.items():
        found += numbers_of(info.annotation, list(info.metadata), prefix + name.upper())
    return found


def numbers_of(annotation: Any, metadata: list[object], where: str) -> list[tuple[str, Range]]:
    """The numbers of a field of type ``annotation`` with pydantic ``metadata`` whose
    variable is ``where`` (a tuple's elements ``where[i]``, a nested model's fields
    ``where__NAME``), each with its documented range."""
    annotation, extra = _unannotated(annotation)
    metadata = metadata + extra
    annotation = _without_none(annotation)
    if annotation in (int, float):
        return [(where, range_of(metadata))]
    if inspect.isclass(annotation) and issubclass(annotation, BaseModel):
        return number_fields(annotation, where + "__")
    if typing.get_origin(annotation) is tuple:
        elements = typing.get_args(annotation)
        if len(elements) == 2 and elements[1] is Ellipsis:
            return numbers_of(elements[0], [], f"{where}[i]")
        return [n for i, e in enumerate(elements) for n in numbers_of(e, [], f"{where}[{i}]")]
    return []


def _element(annotation: Any, index: int) -> Any:
    """The type of element ``index`` of a tuple type (None: not a tuple)."""
    elements = typing.get_args(annotation) if typing.get_origin(annotation) is tuple else ()
    if len(elements) == 2 and elements[1] is Ellipsis:
        return elements[0]
    return elements[index] if 0 <= index < len(elements) else None


def _unannotated(annotation: Any) -> tuple[Any, list[object]]:
    """``Annotated[T, ...]`` as T and its metadata."""
    if typing.get_origin(annotation) is Annotated:
        inner, *metadata = typing.get_args(annotation)
        return inner, list(metadata)
    return annotation, []


def _without_none(annotation: Any) -> Any:
    """``T | None`` as T (other unions as they are)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        members = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(members) == 1:
            return members[0]
    return annotation


def ordered(settings: BaseModel, low: str, high: str, *, strict: bool = True) -> None:
    """Refuse a contradictory pair of fields (each a number or a tuple of numbers): every
    element of ``low`` must be below (``strict``) or at most the same element of ``high``.
    The ValueError names the low field's element, its range given the high one, its value
    and the high one (as variables once ``invalid_line`` has named the fields)."""
    lows, highs = getattr(settings, low), getattr(settings, high)
    if not isinstance(lows, tuple):
        pairs = [(lows, highs)]
    else:  # element by element, or every element against one number
        pairs = list(zip(lows, highs, strict=True) if isinstance(highs, tuple) else
                     ((a, highs) for a in lows))  # fmt: skip
    for index, (a, b) in enumerate(pairs):
        if a < b or (a == b and not strict):
            continue
        at = f"[{index}]" if isinstance(lows, tuple) else ""
        high_at = at if isinstance(highs, tuple) else ""
        location = (low, index) if isinstance(lows, tuple) else (low,)
        own = field_range(type(settings), location) or Range()
        bounds = Range(own.lower, b, own.lower_open, strict)
        relation = "below" if strict else "at most"
        raise ValueError(f"{low}{at}={a:g}: outside its range {bounds} ({relation} "
                         f"{high}{high_at}={b:g})")  # fmt: skip


def at_least(settings: BaseModel, name: str, lowest: float, why: str) -> None:
    """Refuse ``name`` below ``lowest``, which other fields set (``why`` says how): one
    line with the variable, the range that follows and the value."""
    value = getattr(settings, name)
    if value < lowest:
        own = field_range(type(settings), (name,)) or Range()
        bounds = Range(lowest, own.upper, False, own.upper_open)
        raise ValueError(f"{name}={value:g}: outside its range {bounds} ({why})")


def _named(settings: type[BaseSettings], message: str, model: type[BaseModel] | None = None,
           location: tuple[int | str, ...] = ()) -> str:  # fmt: skip
    """``message`` with each field name of ``model`` (``settings`` itself, or the nested
    model at ``location``) as its environment variable."""
    model = settings if model is None else model
    for name in sorted(model.model_fields, key=len, reverse=True):
        named = variable(settings, (*location, name))
        message = re.sub(rf"(?<![A-Za-z_\-])\b{name}\b", named, message)
    return message


def _model_at(settings: type[BaseModel], location: tuple[int | str, ...]) -> type[BaseModel] | None:
    """The model (``settings``, or one nested in it) at ``location``; None: a value."""
    current: Any = settings
    for part in location:
        if not (isinstance(part, str) and inspect.isclass(current)
                and issubclass(current, BaseModel) and part in current.model_fields):  # fmt: skip
            return None
        current = _without_none(_unannotated(current.model_fields[part].annotation)[0])
    return current if inspect.isclass(current) and issubclass(current, BaseModel) else None


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
    """A given value as the user typed it (a variable's text unquoted), shortened."""
    typed = isinstance(value, str) and value != "" and not any(c.isspace() for c in value)
    text = str(value) if typed else repr(value)
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
