"""The msgpack envelope every non-frame message travels in.

Layout: a msgpack array ``[MAGIC, kind, major, minor, body]`` where ``body`` is the message's field
map. numpy arrays inside the body are plain maps ``{"dtype", "shape", "data"}`` (see
:mod:`protocol.arrays`; the legacy ext type 1 form is still decoded). docs/WIRE.md is the contract for
readers without Argus; :func:`content_type` names a message's schema for the Zenoh encoding.

``decode`` raises :class:`DecodeError` for anything wrong (random or truncated bytes, wrong magic,
unknown major version, wrong kind, schema violation, oversized arrays) and nothing else, so a
receiver can log, count and carry on.
"""

from __future__ import annotations

from typing import Any, TypeVar, overload

import msgpack
import numpy as np
from pydantic import ValidationError

from protocol import arrays
from protocol.messages import ALL_MESSAGES, Message
from protocol.rooms import ROOM_MESSAGES

MAGIC = "ARG1"
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
"""Largest envelope decode() accepts. (The array cap is :data:`protocol.arrays.MAX_ARRAY_ELEMENTS`.)"""
MSGPACK_MIME = "application/msgpack"

M = TypeVar("M", bound=Message)

REGISTRY: dict[str, type[Message]] = {cls.KIND: cls for cls in ALL_MESSAGES + ROOM_MESSAGES}


class DecodeError(ValueError):
    """Bytes that are not a valid Argus message of the expected kind."""


def register(cls: type[Message]) -> type[Message]:
    """Register a message class (third-party extensions); its KIND must be unique."""
    if not cls.KIND or (cls.KIND in REGISTRY and REGISTRY[cls.KIND] is not cls):
        raise ValueError(f"message kind {cls.KIND!r} is empty or already registered")
    REGISTRY[cls.KIND] = cls
    return cls


def content_type(cls: type[Message], mime: str = MSGPACK_MIME) -> str:
    """The Zenoh encoding string naming ``cls``'s schema: ``application/msgpack;argus/<kind>/<major>.<minor>``."""
    major, minor = cls.SCHEMA
    return f"{mime};argus/{cls.KIND}/{major}.{minor}"


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return arrays.to_wire(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, tuple):
        return list(obj)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> Any:
    if code != arrays.EXT_NDARRAY:
        raise DecodeError(f"unknown msgpack ext type {code}")
    try:
        return arrays.from_ext(data)
    except arrays.ArrayError as e:
        raise DecodeError(str(e)) from None


def encode(msg: Message) -> bytes:
    """Encode a registered message into its envelope."""
    kind = type(msg).KIND
    if REGISTRY.get(kind) is not type(msg):
        raise TypeError(f"{type(msg).__name__} is not a registered message")
    major, minor = type(msg).SCHEMA
    body = msg.model_dump(mode="python")
    return msgpack.packb([MAGIC, kind, major, minor, body], default=_default, use_bin_type=True)


def peek_kind(data: bytes) -> str:
    """The kind named by an envelope, without validating the body."""
    return _unpack(data)[1]


def _unpack(data: bytes | bytearray | memoryview) -> list[Any]:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise DecodeError(f"expected bytes, got {type(data).__name__}")
    if len(data) > MAX_MESSAGE_BYTES:
        raise DecodeError(f"message of {len(data)} bytes exceeds the cap of {MAX_MESSAGE_BYTES}")
    try:
        env = msgpack.unpackb(
            bytes(data),
            raw=False,
            ext_hook=_ext_hook,
            strict_map_key=True,
            max_bin_len=MAX_MESSAGE_BYTES,
            max_str_len=1024 * 1024,
            max_array_len=1024 * 1024,
            max_map_len=1024 * 1024,
        )
    except DecodeError:
        raise
    except Exception as e:  # noqa: BLE001 - msgpack raises many types on hostile input
        raise DecodeError(f"not a msgpack envelope: {type(e).__name__}: {e}") from None
    if not isinstance(env, list) or len(env) != 5 or env[0] != MAGIC:
        raise DecodeError("not an Argus envelope (bad magic or layout)")
    _, kind, major, minor, body = env
    if not isinstance(kind, str) or not isinstance(major, int) or not isinstance(minor, int):
        raise DecodeError("bad envelope header")
    if not isinstance(body, dict):
        raise DecodeError("envelope body is not a map")
    return env


@overload
def decode(data: bytes | bytearray | memoryview) -> Message: ...
@overload
def decode(data: bytes | bytearray | memoryview, expected: type[M]) -> M: ...
def decode(data: bytes | bytearray | memoryview, expected: type[Message] | None = None) -> Message:
    """Decode and validate an envelope.

    ``expected`` pins the message class: any other kind is refused. A newer major version is
    refused; an older or newer minor of the same major is accepted (unknown fields of a newer
    minor are dropped).
    """
    _, kind, major, minor, body = _unpack(data)
    cls = REGISTRY.get(kind)
    if cls is None:
        raise DecodeError(f"unknown message kind {kind!r}")
    if expected is not None and cls is not expected:
        raise DecodeError(f"expected {expected.KIND!r}, got {kind!r}")
    my_major, my_minor = cls.SCHEMA
    if major != my_major:
        raise DecodeError(f"{kind} schema major {major} not supported (this build speaks {my_major})")
    if minor > my_minor:
        body = {k: v for k, v in body.items() if k in cls.model_fields}
    try:
        return cls.model_validate(body)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise DecodeError(
            f"{kind} failed validation: {e.error_count()} error(s): {where + ': ' if where else ''}{first['msg']}"
        ) from None
    except Exception as e:  # noqa: BLE001 - validators may raise anything on hostile data
        raise DecodeError(f"{kind} failed validation: {type(e).__name__}: {e}") from None
