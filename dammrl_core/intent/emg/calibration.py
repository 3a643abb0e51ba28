"""A person's calibration of a wearable sensor: what ``dammrl intent calibrate`` writes and
the LSL intent source loads (JSON, versioned, plain numbers: no pickle, no code)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dammrl_core.errors import ConfigurationError
from dammrl_core.intent.emg.classifier import CrossValidation, LinearClassifier
from dammrl_core.intent.emg.features import per_channel

CALIBRATION_VERSION = 1


class StreamDescription(BaseModel):
    """The LSL stream a calibration was made on (a different one is refused)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    type: str = Field("", max_length=200)
    channel_count: int = Field(ge=1, le=256)
    nominal_srate_hz: float = Field(gt=0, le=20_000)
    source_id: str = Field("", max_length=200)
    hostname: str = Field("", max_length=200)


class EmgCalibration(BaseModel):
    """One person's classifier for one stream, with how well it separated their classes."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    version: Literal[1] = 1
    created: str = Field(max_length=64, description="ISO 8601, UTC")
    participant: str | None = Field(None, max_length=64, description="a pseudonymous id")
    stream: StreamDescription
    features: Literal["emg", "imu"] = Field("emg", description="the feature set")
    window_s: float = Field(ge=0.05, le=1.0)
    hop_s: float = Field(ge=0.01, le=0.5)
    classifier: LinearClassifier
    rest_rms: list[float] = Field(description="each channel's RMS at rest (flat-channel check)")
    cross_validation: CrossValidation

    @model_validator(mode="after")
    def _fits_the_stream(self) -> EmgCalibration:
        channels = self.stream.channel_count
        expected = per_channel(self.features) * channels
        if self.classifier.features != expected or len(self.rest_rms) != channels:
            raise ValueError(
                f"the classifier has {self.classifier.features} features and "
                f"{len(self.rest_rms)} rest levels for {channels} channels"
            )
        if self.hop_s > self.window_s:
            raise ValueError(f"hop_s {self.hop_s} is longer than window_s {self.window_s}")
        return self


def load_calibration(path: Path) -> EmgCalibration:
    """The calibration in ``path``; a one-line ConfigurationError if it cannot be used."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"EMG calibration {path}: cannot read it ({exc})") from None
    if isinstance(data, dict) and data.get("version") != CALIBRATION_VERSION:
        raise ConfigurationError(
            f"EMG calibration {path}: version {data.get('version')!r}, this dammrl reads "
            f"version {CALIBRATION_VERSION} (calibrate again)"
        )
    try:
        return EmgCalibration.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "file"
        raise ConfigurationError(f"EMG calibration {path}: {where}: {first['msg']}") from None


def save_calibration(calibration: EmgCalibration, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(calibration.model_dump_json(indent=1) + "\n")
    return path
