"""Plug-ins the Python way: built-ins plus the installed packages' entry points.

A lab's own intent source or arm driver is a package of its own that declares an entry
point (``dammrl.intent_sources`` or ``dammrl.arm_drivers``) naming an object of its; dammrl
finds it by name at run time, imports it only when it is used, and never needs an edit.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points

from dammrl_core.errors import DammrlError


def discover(group: str, built_in: dict[str, str]) -> dict[str, str]:
    """Every plug-in's name and where it lives ("module:object"): the built-ins, then the
    entry points of ``group`` (a package cannot shadow a built-in)."""
    found = dict(built_in)
    for entry in entry_points(group=group):
        found.setdefault(entry.name, entry.value)
    return found


def origins(group: str, built_in: dict[str, str]) -> dict[str, str]:
    """Every plug-in's name and who provides it ("built-in" or the package's name)."""
    found = dict.fromkeys(built_in, "built-in")
    for entry in entry_points(group=group):
        found.setdefault(entry.name, f"package {entry.dist.name}" if entry.dist else "package")
    return dict(sorted(found.items()))


def load(group: str, built_in: dict[str, str], name: str, what: str) -> object:
    """The plug-in ``name`` of ``group``; a one-line error naming the installed ones."""
    plugins = discover(group, built_in)
    if name not in plugins:
        raise DammrlError(
            f"unknown {what} {name!r}: installed are {sorted(plugins)} (a package adds one "
            f"under the entry-point group {group!r})"
        )
    module, _, attribute = plugins[name].partition(":")
    try:
        target: object = importlib.import_module(module)
        for part in attribute.split("."):
            target = getattr(target, part)
    except (ImportError, AttributeError) as exc:
        raise DammrlError(f"cannot load the {what} {name!r} ({plugins[name]}): {exc}") from exc
    return target
