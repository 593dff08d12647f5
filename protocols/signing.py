"""MAVLink 2 message signing: the key file, and the check of incoming frames.

A signed frame ends with a 13-byte block: link id, a 48-bit timestamp (10 µs units since
2015-01-01 00:00 UTC) and the first 6 bytes of SHA-256(key ‖ frame up to the timestamp).
We verify frames ourselves rather than through pymavlink's parser because pymavlink records a
stream's timestamp before checking the signature, so a single forged frame with a far-future
timestamp would make every genuine frame after it look like a replay. Here a stream's
timestamp only advances on a frame whose signature is good.

Pure: hashlib and the standard library, no pymavlink (frames are bytes).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from protocols.input_files import not_a_file

KEY_BYTES = 32
SIGNATURE_BLOCK = 13
MARKER_V2 = 0xFD
IFLAG_SIGNED = 0x01
#: 2015-01-01T00:00:00Z, the MAVLink signing epoch.
SIGNING_EPOCH = 1_420_070_400
#: A new stream may start at most this far behind our clock (the MAVLink spec's minute).
NEW_STREAM_SLACK = 60 * 100_000


class SigningKeyError(ValueError):
    """The key file is missing, unreadable or not a 32-byte key."""


def load_key(path: str | Path) -> bytes:
    """Read a 32-byte key: raw bytes, or 64 hexadecimal characters (whitespace ignored).

    The key is never echoed in errors. A key readable by group or others is refused, as
    ssh does for private keys: anyone who can read it can command the vehicle.
    """
    path = Path(path)
    problem = not_a_file(path, "signing key file")
    if problem:
        raise SigningKeyError(f"cannot read signing key {problem}")
    try:
        data = path.read_bytes()
        mode = path.stat().st_mode
    except OSError as error:
        raise SigningKeyError(f"cannot read signing key {path}: {error.strerror}") from None
    if os.name == "posix" and mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SigningKeyError(
            f"signing key {path} is accessible by group or others; chmod 600 {path}"
        )
    if len(data) == KEY_BYTES:
        return data
    text = b"".join(data.split())
    if len(text) == 2 * KEY_BYTES:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningKeyError(
        f"signing key {path} must hold {KEY_BYTES} raw bytes or {2 * KEY_BYTES} hex digits "
        f"(found {len(data)} bytes)"
    )


def signing_timestamp(now: float | None = None) -> int:
    """Wall-clock time in MAVLink signing units (10 µs since 2015-01-01)."""
    seconds = time.time() if now is None else now
    return max(0, int((seconds - SIGNING_EPOCH) * 100_000))


def sign_frame(frame: bytes, key: bytes) -> bytes:
    """The 6-byte signature of a frame whose last 7 bytes are link id and timestamp."""
    return hashlib.sha256(key + frame).digest()[:6]


@dataclass
class SigningCounters:
    signed_accepted: int = 0
    unsigned_accepted: int = 0
    unsigned_rejected: int = 0
    bad_signature: int = 0
    replayed: int = 0  # timestamp not newer than the stream's last, or far too old

    def as_dict(self) -> dict[str, int]:
        return {f"signing_{name}": value for name, value in self.__dict__.items()}

    @property
    def rejected(self) -> int:
        return self.unsigned_rejected + self.bad_signature + self.replayed


@dataclass
class FrameVerifier:
    """Decides whether an incoming MAVLink 2 frame is accepted, and counts why not.

    ``accept_unsigned`` lets unsigned frames through, except the message ids in
    ``always_signed`` (a vehicle that takes unsigned heartbeats from a ground station must
    still refuse unsigned commands). Replay does not verify at all: it reads only the frames
    the live service accepted (``mavlink/raw/in``), so old timestamps never matter there.
    """

    key: bytes
    accept_unsigned: bool = False
    always_signed: frozenset[int] = frozenset()
    clock: Callable[[], float] = time.time
    counters: SigningCounters = field(default_factory=SigningCounters)
    last_reason: str = ""
    _streams: dict[tuple[int, int, int], int] = field(default_factory=dict)

    def accept(self, frame: bytes) -> bool:
        if len(frame) < 12 or frame[0] != MARKER_V2:
            return self._reject_unsigned(-1)
        msg_id = frame[7] | frame[8] << 8 | frame[9] << 16
        if not frame[2] & IFLAG_SIGNED or len(frame) < 12 + SIGNATURE_BLOCK:
            return self._reject_unsigned(msg_id)
        signed_part, signature = frame[:-6], frame[-6:]
        if not hmac.compare_digest(sign_frame(signed_part, self.key), signature):
            self.counters.bad_signature += 1
            self.last_reason = "bad signature"
            return False
        stream = (frame[-13], frame[5], frame[6])  # link id, system, component
        timestamp = int.from_bytes(frame[-12:-6], "little")
        last = self._streams.get(stream)
        if last is not None and timestamp <= last:
            self.counters.replayed += 1
            self.last_reason = f"replayed timestamp on stream {stream}"
            return False
        if last is None and timestamp + NEW_STREAM_SLACK < signing_timestamp(self.clock()):
            self.counters.replayed += 1
            self.last_reason = f"stream {stream} starts more than 60 s in the past"
            return False
        self._streams[stream] = timestamp
        self.counters.signed_accepted += 1
        return True

    def _reject_unsigned(self, msg_id: int) -> bool:
        if self.accept_unsigned and msg_id not in self.always_signed and msg_id >= 0:
            self.counters.unsigned_accepted += 1
            return True
        self.counters.unsigned_rejected += 1
        self.last_reason = f"unsigned message id {msg_id}"
        return False
