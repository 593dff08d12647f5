"""The fast frame decoder gives exactly pymavlink's message, or defers to pymavlink."""

from __future__ import annotations

import random

import pytest

from protocols.frame_decoder import FrameDecoder
from protocols.mavlink_io import MavlinkCodec, dialect, frame_of, header_of, system_of, type_of

#: Every message type of the dialect that the fast decoder handles (no text fields).
FAST_TYPES = sorted(
    (cls for cls in dialect.mavlink_map.values() if "char" not in cls.fieldtypes),
    key=lambda cls: cls.id,
)


def random_frames(message_class, count: int, seed: int, signed: bool = False) -> list[bytes]:
    """Frames of ``message_class`` with random payload bytes, packed by pymavlink itself."""
    rng = random.Random(seed)
    size = message_class.unpacker.size
    codec = MavlinkCodec(rng.randrange(1, 255), rng.randrange(1, 255), signing_key=(
        bytes(range(32)) if signed else None
    ))  # fmt: skip
    frames = []
    for k in range(count):
        # Some all-zero tails, so that MAVLink 2's truncation of trailing zeros is exercised.
        payload = bytearray(rng.randbytes(size))
        if k % 2:
            cut = rng.randrange(size)
            payload[cut:] = bytes(size - cut)
        fields = dialect.MAVLink(None).decode(
            bytearray(_frame_around(message_class, bytes(payload)))
        )
        frames.append(codec.pack(fields))
    return frames


def _frame_around(message_class, payload: bytes) -> bytes:
    """A valid unsigned frame carrying ``payload`` as is (to let pymavlink decode fields)."""
    header = bytes([0xFD, len(payload), 0, 0, 0, 1, 1]) + message_class.id.to_bytes(3, "little")
    crc = dialect.x25crc(header[1:] + payload + bytes([message_class.crc_extra])).crc
    return header + payload + crc.to_bytes(2, "little")


def same_message(fast, reference) -> bool:
    return (
        type(fast) is type(reference)
        and vars(fast).keys() == vars(reference).keys()
        and all(_same(vars(fast)[k], vars(reference)[k]) for k in vars(reference))
    )


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        return True  # NaN payload bytes decode to NaN in both
    if isinstance(a, dialect.MAVLink_header):
        return vars(a) == vars(b)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@pytest.mark.parametrize("signed", [False, True])
def test_every_fast_type_decodes_exactly_as_pymavlink(signed: bool) -> None:
    assert len(FAST_TYPES) > 100  # the dialect's bulk, not a handful
    decoder = FrameDecoder(dialect)
    reference = dialect.MAVLink(None)
    for message_class in FAST_TYPES:
        for frame in random_frames(message_class, 6, seed=message_class.id, signed=signed):
            fast = decoder.decode(frame)
            assert fast is not None, message_class.msgname
            expected = reference.decode(bytearray(frame))
            assert same_message(fast, expected), message_class.msgname


def test_text_types_are_left_to_pymavlink() -> None:
    codec = MavlinkCodec(1, 1)
    frame = codec.pack(dialect.MAVLink_statustext_message(4, b"pump fault", 0, 0))
    assert FrameDecoder(dialect).decode(frame) is None
    (message,) = codec.parse(frame, datagram=True)  # the codec falls back and decodes it
    assert message.text == "pump fault"


def test_corrupt_or_odd_frames_give_none() -> None:
    decoder = FrameDecoder(dialect)
    (frame,) = random_frames(dialect.MAVLink_attitude_message, 1, seed=1)
    bad_crc = bytearray(frame)
    bad_crc[12] ^= 0x40
    unknown_id = bytearray(frame)
    unknown_id[7:10] = (0xFFFFF0).to_bytes(3, "little")
    for broken in (bytes(bad_crc), frame[:-1], frame + b"\x00", bytes(unknown_id), b"\xfd"):
        assert decoder.decode(broken) is None


def test_codec_results_are_the_same_on_both_paths() -> None:
    """Datagrams of whole frames (fast) and the same bytes as a stream (pymavlink)."""
    frames = [f for cls in FAST_TYPES[:40] for f in random_frames(cls, 2, seed=cls.id)]
    fast_codec, stream_codec = MavlinkCodec(255, 191), MavlinkCodec(255, 191)
    fast = [m for f in frames for m in fast_codec.parse(f, datagram=True)]
    slow = stream_codec.parse(b"".join(frames), datagram=False)
    assert len(fast) == len(slow) == len(frames)
    assert all(same_message(a, b) for a, b in zip(fast, slow, strict=True))
    assert fast_codec.counters.as_dict() == stream_codec.counters.as_dict()


def test_the_codecs_accessors_answer_what_pymavlinks_methods_answer():
    """``type_of``, ``header_of``, ``system_of`` and ``frame_of`` read the attributes behind
    pymavlink's accessors: for every message type of the dialect, decoded from the wire,
    they give what the accessors give."""
    codec = MavlinkCodec(1, 1)
    messages = []
    for seed, message_class in enumerate(sorted(dialect.mavlink_map.values(), key=lambda c: c.id)):
        if "char" in message_class.fieldtypes:
            continue  # random bytes are no text; the fast types cover the accessors
        messages += codec.parse(random_frames(message_class, 1, seed)[0], datagram=True)
    assert len(messages) > 100
    for message in messages:
        assert type_of(message) == message.get_type()
        assert header_of(message) is message.get_header()
        assert system_of(message) == message.get_srcSystem()
        assert frame_of(message) == bytes(message.get_msgbuf())
