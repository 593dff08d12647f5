"""Decoded MAVLink as JSON, with a JSON Schema per message type (for MCAP ``json`` channels).

Encoded with ``protocols.payload_json``, which writes non-finite floats (MAVLink uses NaN
for "unset" parameters) as ``null``, so every payload is strict JSON that any reader,
Foxglove included, can parse.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from protocols.mavlink_io import MavMessage, dialect, header_of, type_of

_INTEGER_TYPES = {"int8_t", "uint8_t", "int16_t", "uint16_t", "int32_t", "uint32_t",
                  "int64_t", "uint64_t", "uint8_t_mavlink_version"}  # fmt: skip


#: Per message class: its field names in declared order, and those of its text fields.
_FIELDS: dict[type, tuple[tuple[str, ...], tuple[str, ...]]] = {}


def _fields_of(message_class: Any) -> tuple[tuple[str, ...], tuple[str, ...]]:
    fields = _FIELDS.get(message_class)
    if fields is None:
        names = tuple(message_class.fieldnames)
        text = tuple(
            name
            for name, ftype in zip(names, message_class.fieldtypes, strict=True)
            if ftype == "char"
        )
        fields = _FIELDS[message_class] = (names, text)
    return fields


def message_to_json(message: MavMessage) -> dict[str, Any]:
    """Fields of ``message`` plus its header: type, source system and component, sequence.

    Floats are left as they are: ``payload_json.encode`` writes NaN (MAVLink's "unset") as
    ``null``. pymavlink's decoder gives text fields as ``str``; a message built another way
    may hold ``bytes``, which are decoded with replacement so that it can still be encoded.
    """
    names, text = _fields_of(type(message))
    # The fields are instance attributes (pymavlink's __init__ and FrameDecoder set them
    # so): read from the instance's dict, without an attribute lookup through the class
    # for each; a field found elsewhere is read as an attribute.
    values = message.__dict__
    try:
        payload = {name: values[name] for name in names}
    except KeyError:
        payload = {name: getattr(message, name) for name in names}
    for name in text:
        if isinstance(payload[name], bytes):
            payload[name] = payload[name].decode("utf-8", "replace")
    header = header_of(message)
    payload["_header"] = {
        "type": type_of(message),
        "system_id": header.srcSystem,
        "component_id": header.srcComponent,
        "seq": header.seq,
    }
    return payload


def _field_schema(field_type: str, array_length: int) -> dict[str, Any]:
    if field_type == "char":
        return {"type": "string"}
    base: dict[str, Any] = (
        {"type": "integer"} if field_type in _INTEGER_TYPES else {"type": ["number", "null"]}
    )
    if array_length:
        return {"type": "array", "items": base, "maxItems": array_length}
    return base


@cache
def message_schema(message_type: str) -> dict[str, Any]:
    """JSON Schema of ``message_to_json`` output for a ``common`` dialect message type."""
    cls = getattr(dialect, f"MAVLink_{message_type.lower()}_message")
    # pymavlink lists array lengths in wire order (ordered_fieldnames), types in declaration
    # order (fieldnames): pair each by name.
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    properties = {
        name: _field_schema(ftype, lengths[name])
        for name, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True)
    }
    properties["_header"] = {
        "type": "object",
        "properties": {
            "type": {"type": "string"},
            "system_id": {"type": "integer"},
            "component_id": {"type": "integer"},
            "seq": {"type": "integer"},
        },
    }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"MAVLink {message_type} (common dialect)",
        "type": "object",
        "properties": properties,
        "required": list(cls.fieldnames),
    }
