"""Recorder settings: one class, environment prefix ``DAMMRL_RECORDER_``."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.settings import Settings


class RecorderSettings(Settings):
    """Where and how the bus is recorded to MCAP."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_RECORDER_")

    out: Path = Path("sessions")
    """A .mcap file, or a directory that receives session-<UTC time>.mcap files."""
    max_bytes: int | None = Field(None, ge=1_000_000, le=10**12)
    """Start a new file once the current one holds this many bytes (None: never; 1 MB -
    1 TB)."""
    max_duration_s: float | None = Field(None, ge=1.0, le=7 * 86_400)
    """Start a new file after this long (None: never) [s] (1 s - a week)."""
    chunk_bytes: int = Field(1_000_000, ge=4096, le=256 << 20)
    """A chunk is closed once it holds this many (uncompressed) bytes..."""
    chunk_s: float = Field(0.5, ge=0.05, le=60)
    """... or once it is this old, and closed chunks are handed to the OS at once: a
    ``kill -9`` loses at most about this much [s]."""
    retry_s: float = Field(5.0, ge=0.1, le=3600)
    """After a write error (disk full), try a new file this often [s]."""
    mode: str = "virtual"
    """Stack mode written into the recording's metadata."""
    study: str = Field("", max_length=4096)
    """The session this recording belongs to (participant, session, protocol and its
    SHA-256, as JSON from ``dammrl session run``), written into the metadata; empty: none."""


SETTINGS: tuple[type[Settings], ...] = (RecorderSettings,)
"""Every settings class this service reads (the launcher checks them before a start)."""
