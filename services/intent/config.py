"""Intent settings (simulated human): one class, environment prefix ``DAMMRL_INTENT_``."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl.core.human import HumanModel
from dammrl.core.models import ModelSet
from dammrl.core.settings import Settings
from services.intent.decoder import DecoderSettings


class IntentSettings(Settings):
    """Where the human's decisions come from (``DAMMRL_INTENT_``).

    The simulated human's behaviour is the stack's one ``DAMMRL_HUMAN_*`` setting
    (:class:`dammrl.core.human.HumanModel`), the radii the one ``DAMMRL_MODELS_*``.
    """

    model_config = SettingsConfigDict(env_prefix="DAMMRL_INTENT_")

    source: Literal["simulated", "serial"] = "simulated"
    """Who decides: the simulated human (virtual mode) or a pressure sensor (semi-virtual)."""
    port: str | None = None
    """Serial device of the pressure sensor (semi-virtual), e.g. /dev/ttyUSB0."""
    baud_rate: int = Field(115_200, gt=0)
    decoder: DecoderSettings = DecoderSettings()
    """Press thresholds, filter and timing, e.g. DAMMRL_INTENT_DECODER__LONG_PRESS_S=0.7."""
    calibration_file: Path | None = None
    """JSON from `dammrl sensor calibrate`; None: the emulator's default calibration."""
    sensor_stale_s: float = Field(0.5, ge=0.05, le=5.0)
    """No valid frame for this long: the sensor is reported silent [s]."""
    reconnect_max_s: float = Field(5.0, ge=0.1, le=60)
    """Longest wait between attempts to reopen a lost serial device [s]."""
    policy_wait_s: float = Field(0.2, gt=0, le=5.0)
    """How long a decision request waits for the policy's ModelChoice [s]."""


SETTINGS: tuple[type[Settings], ...] = (IntentSettings, HumanModel, ModelSet)
"""Every settings class this service reads (the launcher checks them before a start)."""
