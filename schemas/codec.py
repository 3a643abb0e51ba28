"""The one codec of the bus: msgpack of plain maps and lists, validated on decode.

A client in any language reads a message with any msgpack library: a map of field names
to numbers, strings, booleans, nil, lists and nested maps (the header).
"""

from __future__ import annotations

from typing import TypeVar

import msgpack
from pydantic import ValidationError

from schemas.messages import Message

M = TypeVar("M", bound=Message)


class DecodeError(ValueError):
    """Bytes that are not a valid message of the expected type (the wire contract is a
    leaf: its one error type belongs to it, not to any library above it)."""


def encode(message: Message) -> bytes:
    """msgpack bytes of ``message`` (tuples become lists)."""
    return bytes(msgpack.packb(message.model_dump(mode="python"), use_bin_type=True))


def decode(message_type: type[M], data: bytes) -> M:
    """The ``message_type`` carried by ``data``; DecodeError says what is wrong."""
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
        raise DecodeError(f"not msgpack ({len(data)} bytes): {exc}") from exc
    if not isinstance(obj, dict):
        raise DecodeError(
            f"expected a msgpack map for {message_type.__name__}, got {type(obj).__name__}"
        )
    try:
        return message_type.model_validate(obj)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()[:3]
        )
        raise DecodeError(f"invalid {message_type.__name__}: {problems}") from exc
