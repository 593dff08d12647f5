"""``PROTOCOL_VERSION`` (300), the answer to ``MAV_CMD_REQUEST_PROTOCOL_VERSION``.

A standard message (``minimal.xml``) that the generated ``common`` module of the pinned
pymavlink leaves out; packed here with the standard layout and CRC so the emulator can answer
a ground station's MAVLink 2 handshake. Send only: nothing here decodes it.
"""

from __future__ import annotations

import struct
from typing import Any, ClassVar

from protocols.mavlink_io import dialect

MSG_ID_PROTOCOL_VERSION = 300
CRC_EXTRA = 217  # minimal.xml's CRC_EXTRA for id 300
_PAYLOAD = struct.Struct("<HHH8s8s")


class ProtocolVersionMessage(dialect.MAVLink_message):  # type: ignore[misc]
    id = MSG_ID_PROTOCOL_VERSION
    msgname = "PROTOCOL_VERSION"
    fieldnames: ClassVar[list[str]] = [
        "version",
        "min_version",
        "max_version",
        "spec_version_hash",
        "library_version_hash",
    ]
    ordered_fieldnames: ClassVar[list[str]] = fieldnames

    def __init__(self, version: int, min_version: int, max_version: int):
        dialect.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.version, self.min_version, self.max_version = version, min_version, max_version
        self.spec_version_hash = b"\0" * 8
        self.library_version_hash = b"\0" * 8

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = _PAYLOAD.pack(
            self.version,
            self.min_version,
            self.max_version,
            self.spec_version_hash,
            self.library_version_hash,
        )
        return bytes(self._pack(mav, CRC_EXTRA, payload, force_mavlink1=force_mavlink1))
