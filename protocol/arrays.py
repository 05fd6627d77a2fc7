"""numpy arrays on the wire: one plain msgpack map any msgpack reader understands.

An array travels as ``{"dtype": "<f4", "shape": [N, 3], "data": <bin: the raw C-order bytes>}``.
``dtype`` is a numpy type string, always little-endian (``|`` for one-byte types) and one of
:data:`ALLOWED_DTYPES`; ``data`` holds ``prod(shape) * itemsize`` bytes. Older Argus builds sent the
same three items packed inside msgpack extension type 1 (``[dtype, shape, data]``); decoders still
accept that form (:func:`from_ext`), encoders no longer produce it.

Every array read from the wire, in either form, goes through :func:`from_parts`, which refuses
unknown dtypes, odd shapes, byte lengths that disagree with the shape and arrays over the cap.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

MAX_ARRAY_ELEMENTS = 8 * 1024 * 1024
"""Largest array (element count) a decoder accepts."""
MAX_DIMS = 8
EXT_NDARRAY = 1
"""msgpack extension type code of the legacy compact array form."""
ALLOWED_DTYPES = frozenset({"|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8", "|b1"})
WIRE_KEYS = frozenset({"dtype", "shape", "data"})


class ArrayError(ValueError):
    """An array description that is malformed, not allowed or too large."""


def to_wire(a: np.ndarray) -> dict[str, Any]:
    """The plain-map form of ``a`` (little-endian, C order)."""
    a = np.ascontiguousarray(a)
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def is_wire_array(obj: Any) -> bool:
    """Whether ``obj`` is a map with exactly the keys of the plain array form."""
    return isinstance(obj, dict) and obj.keys() == WIRE_KEYS


def from_parts(dtype_str: Any, shape: Any, raw: Any) -> np.ndarray:
    """The array described by ``dtype``, ``shape`` and raw bytes; raises :class:`ArrayError`."""
    if not isinstance(dtype_str, str) or dtype_str not in ALLOWED_DTYPES:
        raise ArrayError(f"array dtype {dtype_str!r} not allowed")
    if not isinstance(shape, (list, tuple)) or len(shape) > MAX_DIMS:
        raise ArrayError("bad array shape")
    if not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
        raise ArrayError("bad array shape")
    n = int(np.prod(shape, dtype=np.float64)) if shape else 1  # float: huge headers must not wrap around
    if n > MAX_ARRAY_ELEMENTS:
        raise ArrayError(f"array of {n} elements exceeds the cap of {MAX_ARRAY_ELEMENTS}")
    dt = np.dtype(dtype_str)
    if not isinstance(raw, (bytes, bytearray)) or len(raw) != n * dt.itemsize:
        raise ArrayError("array byte length does not match its shape")
    return np.frombuffer(bytes(raw), dtype=dt).reshape(shape).copy()


def from_wire(obj: dict[str, Any]) -> np.ndarray:
    """The array of a plain-map form (see :func:`is_wire_array`)."""
    return from_parts(obj.get("dtype"), obj.get("shape"), obj.get("data"))


def from_ext(data: bytes) -> np.ndarray:
    """The array of a legacy ext-type-1 payload (``msgpack([dtype, shape, data])``)."""
    try:
        parts = msgpack.unpackb(data, raw=False)
    except Exception as e:  # noqa: BLE001 - any failure inside is a malformed array
        raise ArrayError(f"bad array: {e}") from None
    if not isinstance(parts, list) or len(parts) != 3:
        raise ArrayError("bad array: expected [dtype, shape, data]")
    return from_parts(*parts)
