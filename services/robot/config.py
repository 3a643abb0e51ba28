"""The robot service's settings: the library's ``ArmSettings`` (DAMMRL_ARM_), the driver's own
(its prefix; checked when the driver is made) and what it shares with the other services."""

from __future__ import annotations

from dammrl_core.arm.settings import ArmSettings
from dammrl_core.robot import RobotSettings
from dammrl_core.settings import Settings
from dammrl_core.task import TaskSettings

SETTINGS: tuple[type[Settings], ...] = (ArmSettings, TaskSettings, RobotSettings)
"""Every settings class this service reads (the launcher checks them before a start; the
driver's own settings too, see ``dammrl.stack.launch``)."""
