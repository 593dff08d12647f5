"""The fast frame encoder makes exactly pymavlink's frame, and leaves the message as
pymavlink's ``pack`` leaves it; types it does not handle go to pymavlink."""

from __future__ import annotations

import copy
import random

import pytest

from protocols.frame_encoder import FrameEncoder
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.mavlink_json import message_to_json
from protocols.protocol_version import MSG_ID_PROTOCOL_VERSION, ProtocolVersionMessage

#: Every message type of the dialect that the fast encoder handles (no text fields).
FAST_TYPES = sorted(
    (cls for cls in dialect.mavlink_map.values() if "char" not in cls.fieldtypes),
    key=lambda cls: cls.id,
)
PACKED = ("_payload", "_msgbuf", "_crc")


def random_messages(message_class, count: int, seed: int) -> list:
    """Messages of ``message_class`` decoded by pymavlink from random payload bytes, half
    of them with an all-zero tail (MAVLink 2 drops trailing zeros)."""
    rng = random.Random(seed)
    size = message_class.unpacker.size
    messages = []
    for k in range(count):
        payload = bytearray(rng.randbytes(size))
        if k % 2:
            cut = rng.randrange(size)
            payload[cut:] = bytes(size - cut)
        header = bytes([0xFD, size, 0, 0, 0, 1, 1]) + message_class.id.to_bytes(3, "little")
        crc = dialect.x25crc(header[1:] + payload + bytes([message_class.crc_extra])).crc
        frame = bytearray(header + payload + crc.to_bytes(2, "little"))
        messages.append(dialect.MAVLink(None).decode(frame))
    return messages


@pytest.mark.parametrize("message_class", FAST_TYPES, ids=lambda cls: cls.__name__[8:-8])
def test_every_fast_type_encodes_exactly_as_pymavlink(message_class) -> None:
    encoder = FrameEncoder(dialect)
    rng = random.Random(message_class.id)
    for message in random_messages(message_class, 6, message_class.id):
        seq, system, component = rng.randrange(256), rng.randrange(1, 256), rng.randrange(256)
        reference = copy.deepcopy(message)
        packer = dialect.MAVLink(None, srcSystem=system, srcComponent=component)
        packer.seq = seq
        expected = bytes(reference.pack(packer))
        assert encoder.encode(message, seq, system, component) == expected
        assert vars(message.get_header()) == vars(reference.get_header())
        for name in PACKED:
            assert getattr(message, name) == getattr(reference, name), name
            assert type(getattr(message, name)) is type(getattr(reference, name)), name


def test_an_all_zero_payload_keeps_one_byte_as_pymavlink_does() -> None:
    message = dialect.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    frame = FrameEncoder(dialect).encode(message, 0, 1, 1)
    assert frame is not None and frame[1] == 1
    assert frame == bytes(copy.deepcopy(message).pack(dialect.MAVLink(None, 1, 1)))


def test_text_types_are_left_to_pymavlink_and_the_codec_still_frames_them() -> None:
    text = dialect.MAVLink_statustext_message(6, b"ballast: external control", 0, 0)
    assert FrameEncoder(dialect).encode(text, 0, 1, 1) is None
    codec, peer = MavlinkCodec(7, 1), MavlinkCodec(255, 190)
    (received,) = peer.parse(codec.pack(text), datagram=True)
    assert received.text == "ballast: external control" and received.get_srcSystem() == 7


def test_a_message_class_of_our_own_packs_itself_through_the_codec() -> None:
    message = ProtocolVersionMessage(200, 100, 200)
    assert FrameEncoder(dialect).encode(message, 0, 1, 1) is None
    frame = MavlinkCodec(1, 1).pack(message)
    assert frame[0] == 0xFD and int.from_bytes(frame[7:10], "little") == MSG_ID_PROTOCOL_VERSION


def test_the_codec_sequence_and_logged_json_match_pymavlink_on_both_paths() -> None:
    """Each sent frame, and the JSON the log keeps of the sent message, as pymavlink's."""
    codec = MavlinkCodec(3, 191)
    packer = dialect.MAVLink(None, srcSystem=3, srcComponent=191)
    messages = [
        dialect.MAVLink_command_long_message(1, 1, 187, 0, 0.5, -0.25, 0, 0, 0, 0, 0),
        dialect.MAVLink_system_time_message(0, 123_000),
        dialect.MAVLink_statustext_message(4, b"hello", 0, 0),
    ] * 100  # past 255: the sequence wraps
    for message in messages:
        reference = copy.deepcopy(message)
        expected = bytes(reference.pack(packer))
        packer.seq = (packer.seq + 1) % 256
        assert codec.pack(message) == expected
        assert message_to_json(message) == message_to_json(reference)


def test_a_signed_codec_signs_through_pymavlink() -> None:
    key = bytes(range(32))
    sender = MavlinkCodec(9, 191, signing_key=key)
    receiver = MavlinkCodec.for_link(255, 190, key)
    frame = sender.pack(dialect.MAVLink_system_time_message(0, 5_000))
    assert frame[2] & dialect.MAVLINK_IFLAG_SIGNED
    (message,) = receiver.parse(frame, datagram=True)
    assert message.time_boot_ms == 5_000 and not receiver.last_rejected
