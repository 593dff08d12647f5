"""The one JSON encoder for every payload the service publishes or logs, per sample.

orjson, not the standard library: a U-model estimate carries about 45 floats, and each
plant step publishes three payloads and logs four decoded MAVLink messages. CPython's
``json`` spends most of that time in float formatting (about 20 µs for one estimate). orjson
writes the same shortest round-trip floats about 20 times faster, and the service's
10,000 samples/s target needs that.

Output is compact JSON (no spaces). Non-finite floats come out as ``null`` (strict JSON)
and never raise: the identifiers never emit them, and if a bug let one through, a
subscriber would see ``null`` and the service would keep running. numpy scalars are
encoded as numbers.
"""

from __future__ import annotations

import math
from typing import Any

import orjson

__all__ = ["decode", "encode", "is_finite_number"]

_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


def encode(payload: Any) -> bytes:
    """``payload`` as UTF-8 JSON bytes (dict keys must be strings)."""
    return orjson.dumps(payload, option=_OPTIONS)


def decode(data: bytes | str) -> Any:
    """Parse JSON bytes or text (raises ``ValueError`` on malformed input)."""
    return orjson.loads(data)


def is_finite_number(value: Any) -> bool:
    """Whether a decoded value (JSON, TOML) is a finite number: an int or a float, not a
    bool (which Python counts as an int), not NaN or infinite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
