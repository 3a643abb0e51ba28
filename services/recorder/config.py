"""Recorder settings: one class, environment prefix ``DAMMRL_RECORDER_``."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl.core.settings import Settings


class RecorderSettings(Settings):
    """Where and how the bus is recorded to MCAP."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_RECORDER_")

    out: Path = Path("sessions")
    """A .mcap file, or a directory that receives session-<UTC time>.mcap files."""
    max_bytes: int | None = Field(None, ge=1_000_000)
    """Start a new file once the current one holds this many bytes (None: never)."""
    max_duration_s: float | None = Field(None, gt=0)
    """Start a new file after this long (None: never) [s]."""
    chunk_bytes: int = Field(1_000_000, ge=4096)
    """MCAP chunk size; a crash loses at most the chunk being written."""
    mode: str = "virtual"
    """Stack mode written into the recording's metadata."""
