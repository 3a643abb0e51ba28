"""The sim service's settings: the library's ``SimSettings`` (DAMMRL_SIM_) and what it shares."""

from __future__ import annotations

from dammrl_core.robot import RobotSettings
from dammrl_core.settings import Settings
from dammrl_core.sim.settings import SimSettings
from dammrl_core.task import TaskSettings

SETTINGS: tuple[type[Settings], ...] = (SimSettings, TaskSettings, RobotSettings)
"""Every settings class this service reads (the launcher checks them before a start)."""
