"""Intent settings (simulated human): one class, environment prefix ``DAMMRL_INTENT_``."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from dammrl.models import ModelSet
from services.intent.decoder import DecoderSettings


class HumanSettings(BaseSettings):
    """The stochastic human of paper section 3.4: accuracy and decision time per radius.

    Decision times are lognormal: median ``decision_median_*_s``, log-sd
    ``decision_sigma``, never below ``decision_min_s`` (choice reaction times of healthy
    adults are 0.3-0.6 s; a hurried choice under E_big is faster and less accurate).
    """

    model_config = SettingsConfigDict(
        env_prefix="DAMMRL_INTENT_", env_nested_delimiter="__", frozen=True, extra="forbid"
    )

    accuracy_big: float = Field(0.8, ge=0, le=1)
    """Probability of a correct command (toward the goal) under E_big."""
    accuracy_small: float = Field(0.9, ge=0, le=1)
    """Probability of a correct command under E_small."""
    decision_median_big_s: float = Field(0.25, gt=0)
    """Median decision time under E_big [s]."""
    decision_median_small_s: float = Field(0.40, gt=0)
    """Median decision time under E_small [s]."""
    decision_sigma: float = Field(0.3, ge=0)
    """Log-standard deviation of the decision time."""
    decision_min_s: float = Field(0.1, ge=0)
    """Shortest possible decision [s]."""
    source: Literal["simulated", "serial"] = "simulated"
    """Who decides: the simulated human (virtual mode) or a pressure sensor (semi-virtual)."""
    port: str | None = None
    """Serial device of the pressure sensor (semi-virtual), e.g. /dev/ttyUSB0."""
    baud_rate: int = Field(115_200, gt=0)
    decoder: DecoderSettings = DecoderSettings()
    """Press thresholds, filter and timing, e.g. DAMMRL_INTENT_DECODER__LONG_PRESS_S=0.7."""
    calibration_file: Path | None = None
    """JSON from `dammrl sensor calibrate`; None: the emulator's default calibration."""
    sensor_stale_s: float = Field(0.5, gt=0)
    """No valid frame for this long: the sensor is reported silent [s]."""
    reconnect_max_s: float = Field(5.0, gt=0)
    """Longest wait between attempts to reopen a lost serial device [s]."""
    policy_wait_s: float = Field(0.2, gt=0)
    """How long a decision request waits for the policy's ModelChoice [s]."""
    models: ModelSet = ModelSet()
