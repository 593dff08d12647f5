"""MAVLink 2 frame encoding for what we send unsigned: pymavlink's frame, byte for byte, at a
fraction of its cost.

pymavlink's ``pack`` strips the payload's trailing zero bytes one at a time in Python (the
glider's ``ACTUATOR_OUTPUT_STATUS`` carries 32 floats, most of them zero) and goes through a
CRC object per frame: four telemetry messages took about 38 µs, more than the service takes
to decode them. Here each message type gets a plan once (its wire-order fields, struct and
CRC extra) and a frame costs one payload pack, one ``rstrip``, one header pack and one CRC.

The message is left as pymavlink's ``pack`` leaves it (``_header``, ``_payload``,
``_msgbuf``, ``_crc``): the log's JSON of a sent message reads its header from there. Types
with text fields are left to pymavlink (their generated ``pack`` encodes the text), and
so is signing (``MavlinkCodec`` signs through pymavlink); ``encode`` then returns None.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from types import ModuleType
from typing import Any

MavMessage = Any  # an instance of one of the dialect's generated message classes

_HEADER = struct.Struct("<BBBBBBBHB")  # magic, len, incompat, compat, seq, sys, comp, id lo/hi
_MAGIC_V2 = 253


@dataclass(frozen=True)
class _Plan:
    """How to turn one message type's fields into its frame's payload."""

    message_id: int
    packer: struct.Struct
    #: (field, array length) in wire order; length 0 marks a scalar.
    wire: tuple[tuple[str, int], ...]
    crc_extra: bytes

    def payload(self, message: MavMessage) -> bytes:
        values: list[Any] = []
        for name, length in self.wire:
            if length:
                values.extend(getattr(message, name))
            else:
                values.append(getattr(message, name))
        return self.packer.pack(*values)


def _plan_for(message_class: Any, dialect: ModuleType) -> _Plan | None:
    if dialect.mavlink_map.get(message_class.id) is not message_class:
        return None  # not the dialect's generated class (PROTOCOL_VERSION): it packs itself
    if "char" in message_class.fieldtypes:
        return None  # text fields are encoded by the generated pack
    return _Plan(
        message_id=message_class.id,
        packer=message_class.unpacker,
        wire=tuple(
            (name, length)
            for name, length in zip(
                message_class.ordered_fieldnames, message_class.array_lengths, strict=True
            )
        ),
        crc_extra=bytes((message_class.crc_extra,)),
    )


class FrameEncoder:
    """Encodes messages as unsigned MAVLink 2 frames (``protocols.mavlink_io`` passes the
    dialect, so that pymavlink stays imported in one place)."""

    def __init__(self, dialect: ModuleType) -> None:
        self._dialect = dialect
        self._plans: dict[type, _Plan | None] = {}
        fast_crc = getattr(dialect, "mcrf4xx", None)
        if fast_crc is not None:
            self._crc = lambda data: fast_crc(data, 0xFFFF)
        else:
            self._crc = lambda data: dialect.x25crc(data).crc

    def _plan(self, message_class: type) -> _Plan | None:
        try:
            return self._plans[message_class]
        except KeyError:
            plan = _plan_for(message_class, self._dialect)
            self._plans[message_class] = plan
            return plan

    def encode(self, message: MavMessage, seq: int, system: int, component: int) -> bytes | None:
        """The unsigned frame pymavlink's ``pack`` makes of ``message`` with this sequence
        number and identity, or None for a type left to pymavlink."""
        plan = self._plan(type(message))
        if plan is None:
            return None
        payload = plan.payload(message)
        # MAVLink 2 drops the payload's trailing zero bytes, keeping at least one.
        payload = payload.rstrip(b"\0") or payload[:1]
        message_id = plan.message_id
        length = len(payload)
        header = _HEADER.pack(
            _MAGIC_V2, length, 0, 0, seq, system, component, message_id & 0xFFFF, message_id >> 16
        )
        body = header + payload
        crc = self._crc(body[1:] + plan.crc_extra)
        frame = body + struct.pack("<H", crc)
        attributes = message.__dict__
        attributes["_header"] = self._dialect.MAVLink_header(
            message_id, 0, 0, length, seq, system, component
        )
        attributes["_payload"] = payload
        attributes["_msgbuf"] = bytearray(frame)
        attributes["_crc"] = crc
        return frame
