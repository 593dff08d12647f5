"""Fuzzing the service's decode path: arbitrary bytes and well-formed but absurd MAVLink.

The path is the live one (``HilService.process_datagram``: codec → assembler → identifiers
→ controller), in-process. Longer runs: ``GLIDER_HIL_FUZZ_EXAMPLES=20000 .venv/bin/python
-m pytest tests/test_fuzz_decode.py`` (the default keeps ``make test`` fast).
"""

from __future__ import annotations

import math
import os
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from hil_service.service import HilService
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.samples import TelemetrySample

EXAMPLES = int(os.environ.get("GLIDER_HIL_FUZZ_EXAMPLES", "150"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
MAPPING = TelemetryMapping()
MAX_FRAME = 280  # MAVLink 2: 10 header + 255 payload + 2 CRC + 13 signature


class CapturingBus(Listener):
    def __init__(self) -> None:
        self.published: list[tuple[str, dict[str, Any]]] = []

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        self.published.append((key, payload))


def _service(control: bool = True) -> tuple[HilService, CapturingBus, Inbox]:
    bus, inbox = CapturingBus(), Inbox()
    service = HilService(ServiceConfig(control_default=control), bus, inbox)
    for system_id in range(1, 4):
        inbox.set_setpoint(system_id, "depth", 16.0)
    return service, bus, inbox


def _all_finite(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_all_finite(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_all_finite(v) for v in value)
    return True


def _good_steps(codec: MavlinkCodec, start_ms: int, n: int) -> list[bytes]:
    frames = []
    for k in range(n):
        sample = TelemetrySample(1, start_ms + 1000 * k, 15.0 + 0.1 * k, 0.01 * k, 0.1, -0.1)
        frames += [codec.pack(m) for m in MAPPING.encode_telemetry(sample)]
    return frames


@FUZZ
@given(st.lists(st.binary(min_size=0, max_size=300), max_size=20))
def test_arbitrary_datagrams_never_raise_or_wedge_the_parser(datagrams):
    service, bus, _ = _service()
    for data in datagrams:
        service.process_datagram(data)
    before = service.source.assembler.counters.samples
    # Whatever came before, whole datagrams of good telemetry are decoded again at once.
    for frame in _good_steps(MavlinkCodec(1, 1), 10**9, 3):
        service.process_datagram(frame)
    assert service.source.assembler.counters.samples >= before + 2
    assert all(_all_finite(payload) for _, payload in bus.published)


@FUZZ
@given(st.binary(min_size=1, max_size=400))
def test_garbage_on_a_stream_link_costs_at_most_one_frame_length(garbage):
    """A stray 0xFD reads a length from the next byte and may swallow up to one maximum
    frame (280 bytes) of what follows, as in any MAVLink parser; nothing after that is lost."""
    service, _, _ = _service()
    steps = [_good_steps(MavlinkCodec(1, 1), 1000 * k, 1) for k in range(12)]
    offset = len(garbage)
    safe = 0
    for frames in steps:
        if offset >= len(garbage) + MAX_FRAME:
            safe += 1
        offset += sum(len(f) for f in frames)
    stream = garbage + b"".join(b"".join(frames) for frames in steps)
    service.process_datagram(stream, datagram=False)
    assert safe >= 6
    assert service.source.assembler.counters.samples >= safe


finite_or_not = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([0.0, -0.0, 1e30, -1e30, float("nan"), float("inf"), float("-inf")]),
)


@st.composite
def absurd_messages(draw):
    system_id = draw(st.integers(1, 3))
    stamp = draw(st.integers(0, 2**32 - 1))
    kind = draw(st.sampled_from(["att", "press", "hud", "aos", "ack", "heartbeat"]))
    f = lambda: draw(finite_or_not)  # noqa: E731
    if kind == "att":
        message = dialect.MAVLink_attitude_message(stamp, f(), f(), f(), f(), f(), f())
    elif kind == "press":
        message = dialect.MAVLink_scaled_pressure2_message(
            stamp, f(), f(), draw(st.integers(-32768, 32767))
        )
    elif kind == "hud":
        heading, throttle = draw(st.integers(-32768, 32767)), draw(st.integers(0, 65535))
        message = dialect.MAVLink_vfr_hud_message(f(), f(), heading, throttle, f(), f())
    elif kind == "aos":
        actuators = [f() for _ in range(32)]
        message = dialect.MAVLink_actuator_output_status_message(
            stamp * 1000 % 2**64, draw(st.integers(0, 2**32 - 1)), actuators
        )
    elif kind == "ack":
        message = dialect.MAVLink_command_ack_message(
            draw(st.integers(0, 65535)), draw(st.integers(0, 255))
        )
    else:
        message = MAPPING.heartbeat(vehicle=True)
    return system_id, message


@FUZZ
@given(st.lists(absurd_messages(), min_size=1, max_size=60))
def test_absurd_but_well_formed_messages_are_counted_and_never_reach_the_identifier(items):
    service, bus, _ = _service()
    codecs = {s: MavlinkCodec(s, 1) for s in range(1, 4)}
    for system_id, message in items:
        service.process_datagram(codecs[system_id].pack(message))
    counters = service.codec.counters
    assert counters.frames == len(items)  # every well-formed frame decoded, none lost
    assert counters.bad_frames == 0 and counters.unknown_frames == 0
    stamped = {
        (system_id, message.get_type(), _stamp(message))
        for system_id, message in items
        if message.get_type() in ("ATTITUDE", "SCALED_PRESSURE2", "ACTUATOR_OUTPUT_STATUS")
    }
    steps = {(s, stamp) for s, _, stamp in stamped}
    assembled = service.source.assembler.counters
    assert assembled.samples + assembled.invalid <= len(steps)
    # Nothing non-finite was published, and every published sample is physically sane.
    for key, payload in bus.published:
        assert _all_finite(payload), (key, payload)
        if key.endswith("/telemetry"):
            assert -50.0 <= payload["depth"] <= 11_000.0
            assert abs(payload["u_depth"]) <= 2.0 + 1e-6
        if key.endswith("/command/ballast"):
            for u in (payload["u_depth"], payload["u_pitch"]):
                assert u is None or abs(u) <= 2.0 + 1e-9


def _stamp(message: Any) -> int:
    if message.get_type() == "ACTUATOR_OUTPUT_STATUS":
        return int(message.time_usec) // 1000
    return int(message.time_boot_ms)
