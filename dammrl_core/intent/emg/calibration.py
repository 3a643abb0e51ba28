"""A person's calibration of a wearable sensor: what ``dammrl intent calibrate`` writes and
the LSL intent source loads (JSON, versioned, plain numbers: no pickle, no code).

Version 2 keeps the signal conditioning its classifier was trained with (high-pass,
mains notch, levels relative to rest) and the stream's channel labels and units; a
version 1 file (made before conditioning existed) is still read, and decodes as it was
trained: raw samples, absolute levels."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dammrl_core.errors import ConfigurationError
from dammrl_core.intent.emg.classifier import CrossValidation, LinearClassifier
from dammrl_core.intent.emg.conditioning import Conditioning
from dammrl_core.intent.emg.features import per_channel

CALIBRATION_VERSION: Literal[2] = 2
READABLE_VERSIONS = (1, 2)


MAX_STREAM_CHANNELS = 64
"""The most channels a stream may have: what the bus's raw chunks carry (``SignalChunk``,
schemas.messages.MAX_CHANNELS; a wider stream crashed the intent service at its first
chunk). Refused at calibration, in one line, instead."""


class StreamDescription(BaseModel):
    """The LSL stream a calibration was made on (a different one is refused)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    type: str = Field("", max_length=200)
    channel_count: int = Field(ge=1, le=MAX_STREAM_CHANNELS)
    nominal_srate_hz: float = Field(gt=0, le=20_000)
    source_id: str = Field("", max_length=200)
    hostname: str = Field("", max_length=200)
    channel_labels: list[str] = Field(default_factory=list, max_length=MAX_STREAM_CHANNELS)
    """Each channel's label from the stream's metadata (empty: it had none)."""
    units: list[str] = Field(default_factory=list, max_length=MAX_STREAM_CHANNELS)
    """Each channel's unit from the stream's metadata (empty: it had none)."""

    @model_validator(mode="after")
    def _one_per_channel(self) -> StreamDescription:
        for name in ("channel_labels", "units"):
            values = getattr(self, name)
            if values and len(values) != self.channel_count:
                raise ValueError(f"{len(values)} {name} for {self.channel_count} channels")
        return self


class CueFollowing(BaseModel):
    """How often the muscles were active while rest was cued and while -1 or +1 was
    (shares of labelled windows whose most active channel was ``ACTIVE_OF_REST`` times
    its rest level): a person who follows the cues is active in the one, not the other."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    rest: float = Field(ge=0, le=1)
    commands: float = Field(ge=0, le=1)


class EmgCalibration(BaseModel):
    """One person's classifier for one stream, with how well it separated their classes."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    version: Literal[1, 2] = CALIBRATION_VERSION
    created: str = Field(max_length=64, description="ISO 8601, UTC")
    participant: str | None = Field(None, max_length=64, description="a pseudonymous id")
    stream: StreamDescription
    features: Literal["emg", "imu"] = Field("emg", description="the feature set")
    window_s: float = Field(ge=0.05, le=1.0)
    hop_s: float = Field(ge=0.01, le=0.5)
    conditioning: Conditioning
    classifier: LinearClassifier
    rest_rms: list[float] = Field(description="each channel's RMS at rest, conditioned "
                                  "(flat-channel check)")  # fmt: skip
    rest_level: list[float] = Field(default_factory=list, description="each channel's rest "
                                    "level (median window MAV at rest, conditioned): the gain "
                                    "since calibration is reported against it")  # fmt: skip
    cross_validation: CrossValidation
    cue_following: CueFollowing | None = None
    """None: not measured (levels not relative to rest: an IMU, a version 1 file)."""

    @model_validator(mode="before")
    @classmethod
    def _version_1_decodes_as_trained(cls, data: Any) -> Any:
        """A version 1 classifier was trained on raw samples, absolute levels."""
        if isinstance(data, dict) and data.get("version") == 1 and "conditioning" not in data:
            return data | {"conditioning": Conditioning.none().model_dump()}
        return data

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
        if self.rest_level and len(self.rest_level) != channels:
            raise ValueError(f"{len(self.rest_level)} rest levels for {channels} channels")
        if (problem := self.conditioning.problem(self.stream.nominal_srate_hz)) is not None:
            raise ValueError(problem)
        return self


def load_calibration(path: Path) -> EmgCalibration:
    """The calibration in ``path``; a one-line ConfigurationError if it cannot be used."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"EMG calibration {path}: cannot read it ({exc})") from None
    if isinstance(data, dict) and data.get("version") not in READABLE_VERSIONS:
        raise ConfigurationError(
            f"EMG calibration {path}: version {data.get('version')!r}, this dammrl reads "
            f"versions {', '.join(map(str, READABLE_VERSIONS))} (calibrate again)"
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
