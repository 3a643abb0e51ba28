"""A minimal XDF writer (the format LabRecorder writes), for tests: one file header, then
per stream a header, its samples (each with its timestamp) and a footer. Spec:
https://github.com/sccn/xdf/wiki/Specifications"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np


def _chunk(tag: int, content: bytes) -> bytes:
    body = struct.pack("<H", tag) + content
    return struct.pack("<BQ", 8, len(body)) + body


def _stream_xml(name: str, kind: str, channels: int, rate: float, source_id: str) -> bytes:
    return (f'<?xml version="1.0"?><info><name>{name}</name><type>{kind}</type>'
            f"<channel_count>{channels}</channel_count><nominal_srate>{rate}</nominal_srate>"
            f"<channel_format>float32</channel_format><source_id>{source_id}</source_id>"
            "<hostname>xdf-test</hostname></info>").encode()  # fmt: skip


def write_xdf(path: Path, streams: list[tuple[str, str, float, np.ndarray, np.ndarray]]) -> Path:
    """``streams``: (name, type, rate [Hz], samples (n, channels), timestamps (n,) [s])."""
    out = bytearray(b"XDF:")
    out += _chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>')
    for sid, (name, kind, rate, samples, stamps) in enumerate(streams, start=1):
        channels = samples.shape[1]
        out += _chunk(2, struct.pack("<I", sid) + _stream_xml(name, kind, channels, rate, name))
        for start in range(0, len(samples), 100):
            part = slice(start, start + 100)
            body = bytearray(struct.pack("<I", sid))
            body += struct.pack("<BI", 4, len(samples[part]))
            for row, stamp in zip(samples[part], stamps[part], strict=True):
                body += struct.pack("<Bd", 8, stamp) + np.asarray(row, "<f4").tobytes()
            out += _chunk(3, bytes(body))
        footer = (f'<?xml version="1.0"?><info><first_timestamp>{stamps[0]}</first_timestamp>'
                  f"<last_timestamp>{stamps[-1]}</last_timestamp>"
                  f"<sample_count>{len(stamps)}</sample_count></info>").encode()  # fmt: skip
        out += _chunk(6, struct.pack("<I", sid) + footer)
    Path(path).write_bytes(bytes(out))
    return Path(path)
