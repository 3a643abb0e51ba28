"""The controller service's settings: the library's ``ControllerSettings`` (DAMMRL_CONTROLLER_)
and what it shares with the other services."""

from __future__ import annotations

from dammrl_core.control.settings import ControllerSettings
from dammrl_core.models import ModelSet
from dammrl_core.robot import RobotSettings
from dammrl_core.settings import Settings
from dammrl_core.task import TaskSettings

SETTINGS: tuple[type[Settings], ...] = (ControllerSettings, TaskSettings, RobotSettings, ModelSet)
"""Every settings class this service reads (the launcher checks them before a start)."""
