"""The one module of ours that imports pymavlink.

MAVLink 2 always, with the standard ``common`` dialect: a codec that turns messages into
frames and frames (or garbage) back into messages while counting what it dropped, and a
byte transport opened from a pymavlink connection string (``udpin:``, ``udpout:``, ``tcp:``,
a serial device), so attaching to a real vehicle is a connection string, nothing else.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import time
from dataclasses import dataclass, field
from typing import Any, Final

# mavutil picks its own dialect from the environment at import time; we never use its
# parser, but pin MAVLink 2 so it does not print or negotiate version 1 on our links.
os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as dialect

from protocols.flag_types import MAX_SPIN_WAIT_US
from protocols.frame_decoder import FrameDecoder
from protocols.frame_encoder import FrameEncoder
from protocols.link_address import ACCEPTED_LINKS, normalized, recorded_kind
from protocols.signing import FrameVerifier, signing_timestamp

DIALECT_NAME = "common"
V2_MIN_FRAME = dialect.HEADER_LEN_V2 + 2  # header and checksum, empty payload
#: The dialect's framing constants, as final ints: compiled, a module attribute of the
#: dialect is a dictionary lookup on every read.
_MARKER_V2: Final[int] = dialect.PROTOCOL_MARKER_V2
_SIGNED: Final[int] = dialect.MAVLINK_IFLAG_SIGNED
_SIGNATURE_LENGTH: Final[int] = dialect.MAVLINK_SIGNATURE_BLOCK_LEN
MAVLINK_VERSION = 2

MavMessage = Any  # pymavlink generates one class per message; they share MAVLink_message
#: Where a datagram came from (a UDP socket address), or None on a stream or an unknown peer.
Address = tuple[Any, ...] | None
UDP_MAX_DATAGRAM = 65535
#: SO_RCVBUF asked for on a UDP link. The kernel's default (net.core.rmem_default, often
#: 208 KiB) holds about 270 small datagrams, a quarter of a second of a 1,000-samples/s
#: fleet's telemetry: a reader that stalls longer loses datagrams. The kernel caps the
#: request at net.core.rmem_max.
UDP_RECEIVE_BUFFER = 4 * 1024 * 1024


# ---- what the per-sample path asks of a decoded message ----
# One place for the four questions (its type, header, sender and frame), so that the rest
# of the code never touches pymavlink's attributes. The first three read the attributes
# that pymavlink's accessors return (``get_type`` is ``return self._type``, ``get_header``
# ``return self._header``, ``get_srcSystem`` ``return self._header.srcSystem``): a plant
# step asks them about fifty times, and each call of an accessor is a Python frame, which
# costs several times the attribute read (``tests/test_frame_decoder.py`` checks that they
# agree for every message type of the dialect).


def type_of(message: MavMessage) -> str:
    """``message.get_type()``."""
    return message._type  # type: ignore[no-any-return]


def header_of(message: MavMessage) -> Any:
    """``message.get_header()`` (pymavlink's ``MAVLink_header``)."""
    return message._header


def system_of(message: MavMessage) -> int:
    """``message.get_srcSystem()``."""
    return message._header.srcSystem  # type: ignore[no-any-return]


def frame_of(message: MavMessage) -> bytes:
    """``bytes(message.get_msgbuf())``: the message's frame."""
    return bytes(message._msgbuf)


@dataclass
class ParseCounters:
    """What the codec saw: frames decoded, and bytes or frames it could not use."""

    frames: int = 0
    bad_frames: int = 0
    unknown_frames: int = 0

    def as_dict(self) -> dict[str, int]:
        return {
            "frames": self.frames,
            "bad_frames": self.bad_frames,
            "unknown_frames": self.unknown_frames,
        }


@dataclass
class MavlinkCodec:
    """Encodes and decodes MAVLink 2 frames for one local identity (system, component).

    Decoding is robust: garbage, truncated frames and CRC failures are counted in
    ``counters`` and skipped, never raised.
    """

    system_id: int
    component_id: int
    counters: ParseCounters = field(default_factory=ParseCounters)
    #: Sign every outgoing frame with this 32-byte key (MAVLink 2 signing), link id 0.
    signing_key: bytes | None = None
    #: Check incoming frames' signatures; frames it refuses are not decoded further.
    verifier: FrameVerifier | None = None
    #: Frames the verifier refused during the last ``parse`` call (for the log).
    last_rejected: list[bytes] = field(default_factory=list)

    def __post_init__(self) -> None:
        # Decoding never checks signatures itself (see protocols.signing for why); a second
        # instance with the key does the signing of what we send.
        self._mav = dialect.MAVLink(None, srcSystem=self.system_id, srcComponent=self.component_id)
        self._mav.robust_parsing = True
        self._frames = FrameDecoder(dialect)
        self._encoder = FrameEncoder(dialect)
        self._packer = self._mav
        if self.signing_key is not None:
            self._packer = dialect.MAVLink(
                None, srcSystem=self.system_id, srcComponent=self.component_id
            )
            self._packer.signing.secret_key = self.signing_key
            self._packer.signing.sign_outgoing = True
            self._packer.signing.link_id = 0

    @classmethod
    def for_link(
        cls,
        system_id: int,
        component_id: int,
        signing_key: bytes | None = None,
        *,
        accept_unsigned: bool = False,
        always_signed: frozenset[int] = frozenset(),
    ) -> MavlinkCodec:
        """A codec for one end of a link: with a key it signs what it sends and verifies
        what it receives (see ``FrameVerifier`` for the unsigned-frame options)."""
        verifier = None
        if signing_key is not None:
            verifier = FrameVerifier(
                signing_key, accept_unsigned=accept_unsigned, always_signed=always_signed
            )
        return cls(system_id, component_id, signing_key=signing_key, verifier=verifier)

    def pack(self, message: MavMessage) -> bytes:
        """Frame ``message`` with our identity and the next sequence number (signed if keyed)."""
        packer = self._packer
        if self.signing_key is not None:
            # Never behind the wall clock, always increasing: receivers reject anything else.
            packer.signing.timestamp = max(packer.signing.timestamp, signing_timestamp())
            frame = bytes(message.pack(packer))
        else:
            encoded = self._encoder.encode(message, packer.seq, self.system_id, self.component_id)
            frame = bytes(message.pack(packer)) if encoded is None else encoded
        packer.seq = (packer.seq + 1) % 256  # pymavlink advances it only in send()
        return frame

    def parse(self, data: bytes, datagram: bool = False) -> list[MavMessage]:
        """All complete, valid messages in ``data``.

        On a stream (serial, TCP) a frame may span calls. A datagram holds whole frames
        only, so with ``datagram=True`` whatever is left over at its end is a truncated
        frame: it is counted and dropped, so it cannot swallow the next datagram's frames.
        """
        if not data:
            return []
        if datagram:
            whole = self._decode_whole_frames(data)
            if whole is not None:
                return self._accept(whole)
        try:
            messages = self._mav.parse_buffer(data) or []
        except Exception:  # pymavlink raises on some malformed payloads; count, never crash
            self.counters.bad_frames += 1
            self._reset_parser()
            return []
        if datagram and self._mav.buf_len() > 0:
            self.counters.bad_frames += 1
            self._reset_parser()
        return self._accept(messages)

    def _decode_whole_frames(self, data: bytes) -> list[MavMessage] | None:
        """The messages of a datagram made of nothing but whole, valid MAVLink 2 frames.

        The common case, split into frames by their length bytes and decoded one by one
        (``FrameDecoder``, or pymavlink's own ``decode`` for types with text fields), without
        pymavlink's byte-at-a-time parser. Anything else (garbage, MAVLink 1, a truncated or
        corrupt frame, an unknown message id) gives None, and the caller parses the datagram
        the general way, which counts what it drops.
        """
        frames = []
        end = len(data)
        position = 0
        while position < end:
            if end - position < V2_MIN_FRAME or data[position] != _MARKER_V2:
                return None
            flags = data[position + 2]
            if flags & ~_SIGNED:
                return None  # pymavlink's parser refuses unknown incompat flags
            signature = _SIGNATURE_LENGTH if flags else 0
            size = V2_MIN_FRAME + data[position + 1] + signature
            if position + size > end:
                return None
            frames.append(data[position : position + size])
            position += size
        decoder = self._frames
        messages = []
        for frame in frames:
            message = decoder.decode(frame)
            if message is None:  # a type with text fields, or something wrong with it
                try:
                    message = self._mav.decode(bytearray(frame))
                except Exception:  # CRC or length error: let the general path count it
                    return None
                if type_of(message).startswith("UNKNOWN_"):
                    return None
            messages.append(message)
        return messages

    def _accept(self, messages: list[MavMessage]) -> list[MavMessage]:
        """Count and drop bad, unknown and (with a verifier) refused frames."""
        good = []
        self.last_rejected = []
        for message in messages:
            kind = type_of(message)
            if kind == "BAD_DATA":
                self.counters.bad_frames += 1
                continue
            if kind.startswith("UNKNOWN_"):
                # pymavlink cannot check the CRC of an id it does not know: such frames are
                # as likely garbage as a foreign dialect, and carry nothing we use.
                self.counters.unknown_frames += 1
                continue
            if self.verifier is not None:
                frame = frame_of(message)
                if not self.verifier.accept(frame):
                    self.last_rejected.append(frame)
                    continue
            self.counters.frames += 1
            good.append(message)
        return good

    def _reset_parser(self) -> None:
        self._mav.buf = bytearray()
        self._mav.buf_index = 0
        self._mav.expected_length = dialect.HEADER_LEN_V1 + 2
        self._mav.have_prefix_error = False


#: pymavlink classes that are live byte pipes (everything else it returns reads a file
#: or runs a program).
_LINK_CLASSES = (mavutil.mavudp, mavutil.mavtcp, mavutil.mavtcpin, mavutil.mavserial)


def check_link(connection: str) -> None:
    """Refuse a connection string that names a file rather than a link (``ValueError``).

    pymavlink opens a ``.tlog`` or any existing regular file as a log to read (and runs an
    ``.elf`` or a file under ``/bin/``): none of them has a socket or a device to wait on
    and send to, so the service would fail later with an obscure error.
    """
    kind = recorded_kind(connection)
    if kind:
        raise ValueError(f"{connection} is {kind}, not a link; --mavlink takes {ACCEPTED_LINKS}")


def spin_wait_problem(spin_wait: float) -> str:
    """What is wrong with a spin wait of ``spin_wait`` s, or ''."""
    if not 0.0 <= spin_wait <= MAX_SPIN_WAIT_US * 1e-6:
        return f"--spin-wait must be 0..{MAX_SPIN_WAIT_US} µs, got {spin_wait * 1e6:g}"
    return ""


def readable(fds: list[int], timeout: float, spin: float = 0.0) -> list[int]:
    """The descriptors of ``fds`` readable within ``timeout`` s.

    With ``spin`` > 0 the first ``spin`` s are polled without sleeping. A process that
    sleeps in ``select`` is woken by the scheduler when its datagram arrives; on another
    core that wake-up costs tens of µs (64–68 µs a round trip on a 2-core virtual machine,
    against 14 µs polled), which is most of a lockstep step when the emulator and the
    service each have a core of their own (docs/lockstep.md, "Two cores"). On a shared
    core a spin only delays the peer it waits for: leave it at 0 there."""
    timeout = max(timeout, 0.0)
    if spin > 0.0 and timeout > 0.0:
        spin = min(spin, timeout)
        end = time.perf_counter() + spin
        while True:
            ready, _, _ = select.select(fds, [], [], 0.0)
            if ready:
                return ready
            if time.perf_counter() >= end:
                break
        timeout -= spin
    ready, _, _ = select.select(fds, [], [], timeout)
    return ready


class Link:
    """A byte pipe to a vehicle or a ground station, opened from a pymavlink connection string.

    Only bytes cross this class: parsing, statistics and vehicle state live elsewhere. A
    file (a ``.tlog``, any regular file) is refused with ``ValueError`` before pymavlink
    opens it (see ``check_link``).
    """

    def __init__(
        self,
        connection: str,
        source_system: int = 255,
        source_component: int = 0,
        spin_wait: float = 0.0,
    ):
        connection = normalized(connection)
        self.connection = connection
        check_link(connection)
        problem = spin_wait_problem(spin_wait)
        if problem:
            raise ValueError(problem)
        #: Seconds ``wait`` polls before it sleeps (``readable``).
        self.spin_wait = spin_wait
        try:
            self._file = mavutil.mavlink_connection(
                connection,
                source_system=source_system,
                source_component=source_component,
                autoreconnect=True,
            )
        except OSError as error:
            if error.errno == errno.EADDRINUSE:
                raise OSError(error.errno, "the port is in use by another process") from error
            raise
        if not isinstance(self._file, _LINK_CLASSES):
            kind = type(self._file).__name__
            self._file.close()
            raise ValueError(
                f"{connection} opens as a {kind}, not a link; --mavlink takes {ACCEPTED_LINKS}"
            )
        #: UDP delivers whole frames per datagram; streams may split them anywhere.
        self.datagram = isinstance(self._file, mavutil.mavudp)
        if self.datagram:
            with contextlib.suppress(OSError):
                self._file.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
            if self._file.udp_server:
                # pymavlink binds a listening end with SO_REUSEADDR, which on Linux lets a
                # second socket that sets it too bind the same port and take its unicast
                # datagrams: a second ``serve`` on a vehicle's port would silently take the
                # vehicle. Cleared once bound, a later bind to the port fails (EADDRINUSE).
                self._file.port.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 0)

    def fileno(self) -> int:
        return self._file.fd if self._file.fd is not None else self._file.port.fileno()

    def bound(self) -> str:
        """The connection string with the port this end listens on: a ``udpin:`` or
        ``tcpin:`` link given port 0 has one from the system, which its peer needs to know.
        Any other link, as given."""
        scheme, _, rest = self.connection.partition(":")
        listening = {"udpin": "port", "tcpin": "listen"}.get(scheme)
        if listening is None:
            return self.connection
        try:
            port = int(getattr(self._file, listening).getsockname()[1])
        except (AttributeError, OSError):  # no such socket, or one already closed
            return self.connection
        return f"{scheme}:{rest.rpartition(':')[0]}:{port}"

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for readable data; True when some may be there."""
        try:
            return bool(readable([self.fileno()], timeout, self.spin_wait))
        except (OSError, ValueError):
            return False

    def recv(self) -> bytes:
        """Bytes available now (one datagram for UDP), or b'' when there are none."""
        try:
            data = self._file.recv()
        except OSError:
            return b""
        if not data:
            return b""
        return data if isinstance(data, bytes) else bytes(data, "latin-1")

    def recv_from(self) -> tuple[bytes, Address]:
        """Like ``recv``, with the sender's address when this end listens on UDP (``udpin``),
        so a reply can go back to the peer that spoke (``send_to``); None otherwise."""
        udp = self._file
        if not (self.datagram and udp.udp_server):
            return self.recv(), None
        try:
            data, address = udp.port.recvfrom(UDP_MAX_DATAGRAM)
        except OSError:
            return b"", None
        # pymavlink's own bookkeeping, so ``send`` (to every peer heard) keeps working.
        udp.clients.add(address)
        udp.clients_last_alive[address] = time.time()
        return bytes(data), address

    def send(self, frame: bytes) -> None:
        """To the link's peer (``udpin``: every peer heard from, as pymavlink does)."""
        self._file.write(frame)

    def send_to(self, frame: bytes, address: Address) -> None:
        """To ``address`` (one heard by ``recv_from``) on a listening UDP link; without an
        address, or on any other link, as ``send``."""
        udp = self._file
        if address is None or not (self.datagram and udp.udp_server):
            self.send(frame)
            return
        # As pymavlink's write: a peer gone away is not the sender's error.
        with contextlib.suppress(OSError):
            udp.port.sendto(frame, address)

    def close(self) -> None:
        self._file.close()


# ---- helpers for profiles, the emulator's ground-station manners and tlog import --------
def message_name(message_id: int) -> str | None:
    """The ``common`` dialect's name for a message id, or None when it has none."""
    cls = dialect.mavlink_map.get(message_id)
    return None if cls is None else str(cls.msgname)


def message_id(name: str) -> int:
    """The id of a ``common`` dialect message by name; KeyError when there is none."""
    cls = getattr(dialect, f"MAVLink_{name.lower()}_message", None)
    if cls is None:
        raise KeyError(name)
    return int(cls.id)


def frame_length(data: bytes | bytearray, position: int = 0) -> int | None:
    """The length of the MAVLink 1 or 2 frame starting at ``position`` (from its header),
    or None when no frame starts there or its header is cut off."""
    if position >= len(data):
        return None
    marker = data[position]
    if marker == dialect.PROTOCOL_MARKER_V2:
        if position + 3 > len(data):
            return None
        signed = data[position + 2] & dialect.MAVLINK_IFLAG_SIGNED
        extra = dialect.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0
        return dialect.HEADER_LEN_V2 + data[position + 1] + 2 + extra
    if marker == dialect.PROTOCOL_MARKER_V1:
        if position + 2 > len(data):
            return None
        return dialect.HEADER_LEN_V1 + data[position + 1] + 2
    return None
