"""Who gets a vehicle slot: both assemblers (lockstep ``SampleAssembler``, periodic
``ProfileAssembler``) serve a system only once it completes a step, never a system id that
is no vehicle's (0, the broadcast id), and count what they do not serve.

Messages are packed and parsed as on the wire (``MavlinkCodec``); the service-level tests
feed ``HilService.process_datagram`` in process, as ``serve`` does with each datagram.
"""

from __future__ import annotations

import pytest

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from hil_service.service import HilService
from hil_service.sources.lockstep_assembler import SampleAssembler
from hil_service.sources.periodic_assembler import DROPPED_REASON, ProfileAssembler
from hil_service.vehicle_links import LinkIdentity
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, MavMessage, dialect
from protocols.profiles import load_profile
from protocols.samples import TelemetrySample

MAPPING = TelemetryMapping()
ARDUSUB = load_profile("ardusub")
STAMPED_PER_STEP = 3  # ATTITUDE, SCALED_PRESSURE2, ACTUATOR_OUTPUT_STATUS (VFR_HUD: no clock)
STRAYS = range(100, 132)  # 32 system ids: the default max_vehicles


def _parsed(system_id: int, messages: list[MavMessage]) -> list[MavMessage]:
    """``messages`` sent as ``system_id`` in one datagram, as the service decodes them."""
    codec, reader = MavlinkCodec(system_id, 1), MavlinkCodec(255, 0)
    return reader.parse(b"".join(codec.pack(m) for m in messages), datagram=True)


def _step_datagram(system_id: int, k: int, depth: float = 15.0) -> bytes:
    sample = TelemetrySample(system_id, 1000 + k * 1000, depth, 0.05, 0.1, -0.1)
    codec = MavlinkCodec(system_id, 1)
    return b"".join(codec.pack(m) for m in MAPPING.encode_telemetry(sample))


def _step(system_id: int, k: int, depth: float = 15.0) -> list[MavMessage]:
    """One glider step (lockstep profile) of ``system_id``, stamped (k + 1) s."""
    sample = TelemetrySample(system_id, 1000 + k * 1000, depth, 0.05, 0.1, -0.1)
    return _parsed(system_id, MAPPING.encode_telemetry(sample))


def _stray(system_id: int) -> list[MavMessage]:
    """A single ATTITUDE: part of a step, never a whole one."""
    return _parsed(system_id, [dialect.MAVLink_attitude_message(5000, 0, 0.1, 0, 0, 0, 0)])


def _feed(assembler: SampleAssembler, messages: list[MavMessage]) -> list[TelemetrySample]:
    return [s for s in (assembler.add(m) for m in messages) if s is not None]


def _stream(system_id: int, seconds: float, depth: float = 12.0) -> list[MavMessage]:
    """An ArduSub's streams (10 Hz each, staggered) as the periodic profile reads them."""
    messages: list[MavMessage] = []
    for k in range(int(seconds * 10)):
        ms = 1000 + k * 100
        servos = [1500] * 16
        servos[8] = 1700
        messages += [
            dialect.MAVLink_attitude_message(ms, 0, 0.05, 0, 0, 0.01, 0),
            dialect.MAVLink_scaled_pressure2_message(
                ms + 20, ARDUSUB.pressure.pressure_hpa(depth), 0, 1500, 0
            ),
            dialect.MAVLink_vfr_hud_message(0, 0, 0, 0, -depth, 0.2),
            dialect.MAVLink_servo_output_raw_message((ms + 50) * 1000, 0, *servos),
        ]
    return _parsed(system_id, messages)


def _sampled(assembler: ProfileAssembler, messages: list[MavMessage]) -> list[TelemetrySample]:
    return [s for m in messages for s in assembler.add_all(m)]


def _renumbered(messages: list[MavMessage], link: int) -> list[MavMessage]:
    """As ``serve --vehicle-ids link`` hands them to the assembler."""
    LinkIdentity().admit(messages, (link, ("127.0.0.1", 14550)))
    return messages


def _with_system_id(messages: list[MavMessage], system_id: int) -> list[MavMessage]:
    for message in messages:
        message.get_header().srcSystem = system_id
    return messages


# ---- system id 0 (no vehicle's) -------------------------------------------------------------
@pytest.mark.parametrize("vehicle_id", [0, 256, 2 * 256])  # plain, and link 1, 2 system 0
def test_a_system_id_that_is_no_vehicle_is_counted_and_never_assembled(vehicle_id: int) -> None:
    assembler = SampleAssembler()
    messages = [m for k in range(5) for m in _with_system_id(_step(1, k), vehicle_id)]
    assert _feed(assembler, messages) == []
    assert assembler.system_ids == []
    assert assembler.counters.unknown_system == 5 * STAMPED_PER_STEP
    assert assembler.counters.samples == 0


def test_system_id_0_renumbered_by_link_stays_unserved() -> None:
    assembler = SampleAssembler()
    messages = [m for k in range(3) for m in _renumbered(_step(0, k), link=2)]
    assert _feed(assembler, messages) == []
    assert assembler.counters.unknown_system == 3 * STAMPED_PER_STEP


def test_system_id_0_is_counted_by_the_periodic_assembler() -> None:
    assembler = ProfileAssembler(ARDUSUB)
    assert _sampled(assembler, _stream(0, 2.0)) == []
    assert assembler.system_ids == []
    assert assembler.counters.unknown_system == 4 * 20


@pytest.mark.parametrize(
    ("profile", "vehicle_ids", "source"),
    [
        ("glider", "sysid", None),
        ("glider", "link", (1, ("127.0.0.1", 14550))),
        ("ardusub", "sysid", None),
    ],
)
def test_serve_keeps_running_on_telemetry_from_system_id_0(
    profile: str, vehicle_ids: str, source: tuple[int, tuple[str, int]] | None
) -> None:
    config = ServiceConfig(profile=load_profile(profile), vehicle_ids=vehicle_ids)
    service = HilService(config, Listener(), Inbox())
    if profile == "glider":
        datagrams = [_step_datagram(0, k) for k in range(5)]
    else:
        codec = MavlinkCodec(0, 1)
        datagrams = [codec.pack(m) for m in _stream(1, 2.0)]
    for data in datagrams:
        assert service.process_datagram(data, source=source) == []
    assert service.vehicles == {}
    assert service.source.link_counters()["unknown_system"] > 0
    # The same service still serves a real vehicle.
    if profile == "glider":
        assert sum(len(service.process_datagram(_step_datagram(1, k))) for k in range(5)) == 5


# ---- slots: taken by a first complete step ------------------------------------------------
def test_stray_frames_do_not_take_the_slots_of_a_real_vehicle() -> None:
    assembler = SampleAssembler()  # max_vehicles 32
    for system_id in STRAYS:
        assert _feed(assembler, _stray(system_id)) == []
    samples = _feed(assembler, [m for k in range(10) for m in _step(1, k)])
    assert [s.system_id for s in samples] == [1] * 10
    assert assembler.system_ids == [1]
    counted = assembler.counters
    assert counted.unknown_system == 0
    # Vehicle 1 made a 33rd candidate: the least recently heard stray was dropped with its
    # partial step.
    assert counted.incomplete == 1


def test_stray_frames_do_not_take_the_slots_of_a_real_ardusub() -> None:
    assembler = ProfileAssembler(ARDUSUB)  # max_vehicles 32
    for system_id in STRAYS:
        assert _sampled(assembler, _stray(system_id)) == []
    samples = _sampled(assembler, _stream(1, 3.0))
    assert len(samples) >= 25 and {s.system_id for s in samples} == {1}
    assert assembler.system_ids == [1]
    counted = assembler.counters
    assert counted.unknown_system == 0
    assert counted.reasons.get(DROPPED_REASON) == 1  # the stray least recently heard


def test_candidates_are_bounded_and_each_one_dropped_is_counted() -> None:
    assembler = SampleAssembler(max_vehicles=4)
    for system_id in range(1, 201):
        _feed(assembler, _stray(system_id))
    # Four candidates held; each of the other 196 was dropped with its partial step.
    assert assembler.counters.incomplete == 196
    assert assembler.counters.unknown_system == 0
    samples = _feed(assembler, [m for k in range(3) for m in _step(250, k)])
    assert len(samples) == 3 and assembler.system_ids == [250]


def test_periodic_candidates_are_bounded_and_each_one_dropped_is_counted() -> None:
    assembler = ProfileAssembler(ARDUSUB, max_vehicles=4)
    for system_id in range(1, 201):
        _sampled(assembler, _stray(system_id))
    assert assembler.counters.reasons == {DROPPED_REASON: 196}
    assert len(_sampled(assembler, _stream(250, 2.0))) >= 15
    assert assembler.system_ids == [250]


def test_a_vehicle_beyond_the_cap_is_refused_and_counted() -> None:
    assembler = SampleAssembler()  # max_vehicles 32
    late = 200
    assert _feed(assembler, _step(late, 0)[:1]) == []  # a candidate when the slots fill
    for system_id in range(1, 33):
        assert len(_feed(assembler, _step(system_id, 0))) == 1
    assert len(assembler.system_ids) == 32
    assert assembler.counters.incomplete == 1  # the late vehicle's partial step, dropped
    assert _feed(assembler, [m for k in range(1, 6) for m in _step(late, k)]) == []
    assert late not in assembler.system_ids
    assert assembler.counters.unknown_system == 5 * STAMPED_PER_STEP
    # The vehicles served go on.
    assert len(_feed(assembler, [m for i in range(1, 33) for m in _step(i, 1)])) == 32


def test_a_periodic_vehicle_beyond_the_cap_is_refused_and_counted() -> None:
    assembler = ProfileAssembler(ARDUSUB, max_vehicles=2)
    for system_id in (1, 2):
        assert _sampled(assembler, _stream(system_id, 1.0))
    refused = _stream(3, 1.0)
    assert _sampled(assembler, refused) == []
    assert assembler.system_ids == [1, 2]
    assert assembler.counters.unknown_system == len(refused)


def test_a_first_complete_step_refused_as_invalid_takes_a_slot() -> None:
    assembler = SampleAssembler(max_vehicles=1)
    assert _feed(assembler, _step(5, 0, depth=float("nan"))) == []
    assert assembler.system_ids == [5] and assembler.counters.invalid == 1
    assert _feed(assembler, _step(1, 0)) == []
    assert assembler.counters.unknown_system == STAMPED_PER_STEP


def test_an_explicit_list_beyond_the_cap_is_served_whole_on_periodic_profiles() -> None:
    assembler = ProfileAssembler(ARDUSUB, system_ids=[1, 2, 3], max_vehicles=2)
    for system_id in (1, 2, 3):
        assert _sampled(assembler, _stream(system_id, 1.0))
    assert assembler.system_ids == [1, 2, 3]
    assert _sampled(assembler, _stream(4, 1.0)) == []  # not listed
    assert assembler.counters.unknown_system > 0
