"""The control gate, tested where it acts: ballast commands on the wire.

Every test runs with control enabled and setpoints in force from the vehicle's first sample,
so the only thing between the identifier and the vehicle's actuators is the gate. Over real
sockets a ``serve`` process talks to a simulated vehicle (``GateVehicle``) whose UDP socket
also receives what the service sends: COMMAND_LONG frames are counted there, decoded with
``protocols.mavlink_io``, and the reason the service gives is read from its health on Zenoh.

The vehicle applies its own excitation and ignores the commands, so the identifier sees the
same data whatever the gate lets through: each count below is exact, and each test fails
when the gate condition it covers is removed (checked by hand, and by ``make mutate``).

The in-process tests at the end cover the finer cases (thresholds, boundaries) through
``HilService.process_datagram`` with a link that keeps what is sent.
"""

from __future__ import annotations

import dataclasses
import math
import socket
from collections.abc import Callable

import numpy as np
import pytest

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox, SetpointLimits
from hil_service.listeners import Listener
from hil_service.pipeline import PipelineSettings
from hil_service.service import HilService
from hil_service.umodel import build_model
from plant_emulator.excitation import RandomSteps
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping, is_ballast_command
from protocols.mavlink_io import Link, MavlinkCodec
from protocols.samples import BallastCommand, TelemetrySample
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

MAPPING = TelemetryMapping()
BURN_IN = 60
#: Samples the default identifier spends filling its lags after the first sample.
HISTORY = build_model("dynamic").history_length
#: Samples without a command however good the identifier: lags, then the burn-in.
BLOCKED = HISTORY + BURN_IN - 1
RATE = 0.05  # --max-ballast-rate, model units per step
#: A value that went through the wire's float32 (commands and applied inputs alike).
WIRE = 1e-6


# ---- the simulated vehicle ----------------------------------------------------------------
class GateVehicle:
    """A glider on a UDP socket: sends telemetry, keeps every ballast command it receives.

    Its inputs come from its own excitation (or ``u_depth`` given to ``step``), never from
    the commands, so what the identifier sees does not depend on what the gate let through.
    """

    def __init__(self, port: int, trim_depth: float = 15.0, seed: int = 1):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.address = ("127.0.0.1", port)
        self.codec = MavlinkCodec(1, 1)
        self.reader = MavlinkCodec(1, 1)
        self.plant = GliderPlant(PlantConfig(scenario="paper", seed=seed, trim_depth=trim_depth))
        self.excitation = {
            ch: RandomSteps(amplitude=1.5, min_hold=5, max_hold=20, seed=seed + i)
            for i, ch in enumerate(("depth", "pitch"))
        }
        self.sent: list[TelemetrySample] = []
        #: (samples sent when it was read, command in model units)
        self.commands: list[tuple[int, BallastCommand]] = []

    def next_sample(self) -> TelemetrySample:
        k = self.plant.k
        return self.plant.step(self.excitation["depth"].value(k), self.excitation["pitch"].value(k))

    def send(self, sample: TelemetrySample) -> None:
        for message in MAPPING.encode_telemetry(sample):
            self.sock.sendto(self.codec.pack(message), self.address)
        self.sent.append(sample)

    def drain(self) -> int:
        """Read every datagram waiting; return how many ballast commands they held."""
        before = len(self.commands)
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                return len(self.commands) - before
            for message in self.reader.parse(data, datagram=True):
                if is_ballast_command(message):
                    command = MAPPING.parse_ballast_command(message)
                    self.commands.append((len(self.sent), command))

    def close(self) -> None:
        self.sock.close()


class GateRig:
    """A ``serve`` process with control on, its Zenoh probe and a ``GateVehicle``."""

    def __init__(self, processes, tmp_path, *extra: str, trim_depth: float = 15.0):
        udp, zport = free_udp_port(), free_tcp_port()
        endpoint = f"tcp/127.0.0.1:{zport}"
        self.service = processes.start_service(
            "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
            "--no-log", "--sysid", "1", "--control", "--burn-in", str(BURN_IN), *extra,
        )  # fmt: skip
        self.processes = processes
        self.probe = ZenohProbe(endpoint)
        self.vehicle = GateVehicle(udp, trim_depth=trim_depth)

    # -- inputs ----------------------------------------------------------------------
    def set_setpoints(self, depth: float | None, pitch: float | None) -> None:
        self.probe.put("glider/1/setpoint/depth", {"value": depth})
        self.probe.put("glider/1/setpoint/pitch", {"value": pitch})

    def set_enabled(self, enabled: bool) -> None:
        self.probe.put("glider/1/control", {"enabled": enabled})

    # -- traffic ---------------------------------------------------------------------
    def stream(
        self, n: int, edit: Callable[[int, TelemetrySample], TelemetrySample] | None = None
    ) -> int:
        """Send ``n`` samples (``edit(i, sample)`` may change the i-th); return the commands
        received for them. Paced by the service's telemetry echo so no datagram is dropped."""
        commands = len(self.vehicle.commands)
        for i in range(n):
            sample = self.vehicle.next_sample()
            self.vehicle.send(sample if edit is None else edit(i, sample))
            if i % 20 == 19 or i == n - 1:
                sent = len(self.vehicle.sent)
                assert self.probe.wait_for(
                    lambda sent=sent: self.probe.count("glider/1/telemetry") >= sent, 20
                ), f"the service echoed {self.probe.count('glider/1/telemetry')}/{sent} samples"
                self.vehicle.drain()
        self.settle()
        return len(self.vehicle.commands) - commands

    def settle(self) -> dict:
        """Health published after every sample sent was processed (so every command the
        service sent for them is in the vehicle's socket), with those commands read."""
        sent = len(self.vehicle.sent)
        assert self.probe.wait_for(lambda: self.health().get("samples", -1) >= sent, 20), (
            self.health()
        )
        self.vehicle.drain()
        return self.health()

    def health(self) -> dict:
        return self.probe.latest("glider/1/health", {})

    def wait_health(self, predicate: Callable[[dict], bool], timeout: float = 20) -> dict:
        assert self.probe.wait_for(lambda: predicate(self.health()), timeout), self.health()
        return self.health()

    def close(self) -> None:
        self.vehicle.close()
        self.probe.close()
        _, err = self.processes.stop(self.service)
        assert self.service.returncode == 0, err


@pytest.fixture
def make_rig(processes, tmp_path):
    rigs: list[GateRig] = []

    def make(*extra: str, trim_depth: float = 15.0) -> GateRig:
        rig = GateRig(processes, tmp_path, *extra, trim_depth=trim_depth)
        rigs.append(rig)
        return rig

    yield make
    for rig in rigs:
        rig.close()


def first_sample_with_setpoints(rig: GateRig, depth: float | None, pitch: float | None) -> None:
    """Setpoints put before the first sample, confirmed in force by the health it creates."""
    rig.set_setpoints(depth, pitch)
    assert rig.stream(1) == 0
    rig.wait_health(lambda h: h["control"]["setpoints"] == {"depth": depth, "pitch": pitch})


# ---- on real sockets --------------------------------------------------------------------
@pytest.mark.wire
def test_no_command_before_convergence_then_every_step_within_the_rate(make_rig):
    rig = make_rig("--max-ballast-rate", str(RATE), "--stale-timeout", "30")
    first_sample_with_setpoints(rig, 16.0, 0.05)

    # Up to the last sample of the burn-in: not one frame, and health says why.
    assert rig.stream(BLOCKED - 1) == 0
    health = rig.settle()
    assert health["control"]["enabled"] is True
    assert health["control"]["commanding"] is False
    assert health["control"]["reason"].startswith(
        f"identifier not converged (depth: {BURN_IN - 1}/{BURN_IN} samples"
    ), health["control"]
    assert health["counters"]["commands_sent"] == 0

    # Converged (recent skill ≥ 0 on this data): one command per sample from the next one,
    # pitch's at once; depth's model does not yet predict over its horizon (the horizon
    # test, docs/control.md), so depth holds (NaN) until it does.
    assert rig.stream(40) == 40
    health = rig.settle()
    if health["control"]["commanding"] is False:  # depth may qualify later than pitch
        assert health["control"]["reason"].startswith(
            "model does not predict over the horizon (depth:"
        ), health["control"]
    assert rig.stream(160) == 160
    health = rig.settle()
    # This vehicle ignores the commands, so a loop cannot work: the supervisor may see it
    # and send a channel to its safe input (still a command, at the rate limit).
    reason = health["control"]["reason"]
    assert health["control"]["commanding"] is True or reason.startswith("supervisor: "), reason
    assert health["counters"]["commands_sent"] == 200
    assert health["identifier"]["depth"]["converged"] is True
    assert health["identifier"]["depth"]["horizon_qualified"] is True

    # --max-ballast-rate caps every step on both channels, the first one counted from the
    # input the vehicle reported applying when control took over.
    commands = [c for _, c in rig.vehicle.commands]
    takeover = rig.vehicle.sent[BLOCKED]
    previous = {"depth": takeover.u_depth, "pitch": takeover.u_pitch}
    steps = []
    held = {"depth": False, "pitch": False}
    for i, command in enumerate(commands):
        answered = rig.vehicle.sent[BLOCKED + i]  # one command per sample from here
        for ch, u in (("depth", command.u_depth), ("pitch", command.u_pitch)):
            if not math.isfinite(u):  # a channel not yet qualified holds its input
                assert ch == "depth" and not held["pitch"]
                held[ch] = True
                continue
            if not held[ch]:  # the first command after a hold: from the applied input
                # A re-arm after a supervisor trip takes over from the applied input too
                # (this vehicle ignores commands: the two differ).
                steps.append(min(abs(u - previous[ch]), abs(u - answered.input(ch))))
            held[ch] = False
            previous[ch] = u
    assert not held["depth"], "depth never qualified"
    assert max(steps) <= RATE + WIRE, max(steps)
    assert sum(s > RATE - WIRE for s in steps) >= 5, "the rate limit never bound: test too weak"


@pytest.mark.wire
def test_divergence_stops_commands_until_skill_is_back(make_rig):
    # Near the surface the identifier's error scale is small enough for a burst of absurd
    # (but valid) depths to be declared a divergence within its 10-step test.
    rig = make_rig("--stale-timeout", "30", trim_depth=0.5)
    first_sample_with_setpoints(rig, 1.0, 0.05)
    assert rig.stream(BLOCKED - 1 + 40) == 40  # commanding normally

    # An alternating burst of absurd (but valid) depths. An RLS identifier learns the
    # alternation within a few samples, so its errors alone do not trip the test; its
    # predicted one-step jumps do (see hil_service/umodel/guards.py).
    def burst(i: int, sample: TelemetrySample) -> TelemetrySample:
        return sample._replace(depth=10_000.0 if i % 2 == 0 else 0.0)

    # The first nine burst samples still look like a converged identifier; the tenth
    # trips the divergence test, and depth is not commanded from that sample on. The gate
    # is per channel: pitch's commands go on (depth NaN: the vehicle keeps its input; or
    # depth's safe input if its supervisor caught the burst first).
    assert rig.stream(10, burst) == 10
    health = rig.settle()
    assert health["identifier"]["depth"]["divergences"] == 1
    assert health["control"]["reason"].startswith("identifier diverged (depth)")

    def depth_held(command: BallastCommand) -> bool:
        return math.isnan(command.u_depth) or command.u_depth == 0.0  # NaN or neutral

    assert depth_held(rig.vehicle.commands[-1][1])
    assert math.isfinite(rig.vehicle.commands[-1][1].u_pitch)

    # Back to ordinary data: depth still held, because its identifier must converge again
    # and its recent skill (the burst is in the window) is far below the minimum.
    assert rig.stream(40) == 40
    health = rig.settle()
    assert health["control"]["reason"].startswith("identifier not converged (depth:")
    assert health["identifier"]["depth"]["recent_skill"] < 0
    assert health["counters"]["commands_sent"] == 90
    assert all(depth_held(c) for _, c in rig.vehicle.commands[-40:])


@pytest.mark.wire
def test_low_skill_after_the_burn_in_never_commands(make_rig):
    """A random walk unrelated to the inputs: persistence is the best predictor, so the
    identifier's recent skill stays below the minimum (0) and the gate stays shut."""
    rig = make_rig("--stale-timeout", "30")
    rng = np.random.default_rng(3)
    walk = {"depth": 15.0, "pitch": 0.0}

    def random_walk(i: int, sample: TelemetrySample) -> TelemetrySample:
        walk["depth"] += float(rng.normal(0.0, 0.2))
        walk["pitch"] += float(rng.normal(0.0, 0.01))
        u = float(rng.uniform(-1.0, 1.0))
        return sample._replace(depth=walk["depth"], pitch=walk["pitch"], u_depth=u, u_pitch=-u)

    rig.set_setpoints(16.0, 0.0)
    assert rig.stream(1, random_walk) == 0
    rig.wait_health(lambda h: h["control"]["setpoints"] == {"depth": 16.0, "pitch": 0.0})
    assert rig.stream(BLOCKED + 140, random_walk) == 0
    health = rig.settle()
    depth = health["identifier"]["depth"]
    assert depth["samples"] >= BURN_IN and depth["converged"] is False
    assert depth["recent_skill"] < 0
    assert health["control"]["reason"].startswith(
        f"identifier not converged (depth: {BURN_IN}/{BURN_IN} samples, recent skill -"
    ), health["control"]
    assert health["counters"]["commands_sent"] == 0


@pytest.mark.wire
def test_disabled_no_setpoint_and_stale_telemetry_send_nothing(make_rig):
    rig = make_rig("--max-ballast-rate", str(RATE), "--stale-timeout", "3")
    first_sample_with_setpoints(rig, 16.0, 0.05)
    assert rig.stream(BLOCKED - 1 + 20) == 20

    rig.set_enabled(False)
    rig.wait_health(lambda h: h["control"]["enabled"] is False)
    assert rig.stream(20) == 0
    assert rig.settle()["control"]["reason"] == "control disabled"

    rig.set_enabled(True)
    rig.set_setpoints(None, None)
    rig.wait_health(
        lambda h: (
            h["control"]["enabled"] is True
            and h["control"]["setpoints"] == {"depth": None, "pitch": None}
        )
    )
    assert rig.stream(20) == 0
    assert rig.settle()["control"]["reason"] == "no setpoint"

    rig.set_setpoints(16.0, None)  # depth only: pitch is left unchanged (NaN on the wire)
    rig.wait_health(lambda h: h["control"]["setpoints"] == {"depth": 16.0, "pitch": None})
    assert rig.stream(20) == 20
    last = rig.vehicle.commands[-1][1]
    assert math.isfinite(last.u_depth) and math.isnan(last.u_pitch)

    # Silence: health turns stale, and nothing is sent while no telemetry comes.
    before = len(rig.vehicle.commands)
    health = rig.wait_health(lambda h: h["control"]["reason"] == "telemetry stale")
    assert health["control"]["commanding"] is False
    rig.vehicle.drain()
    assert len(rig.vehicle.commands) == before

    # Telemetry back, with the vehicle's actuator far from the last command: control
    # re-arms from what the vehicle applies, never continues from the stale command.
    applied = -1.0 if last.u_depth > 0 else 1.0

    def far_from_last(i: int, sample: TelemetrySample) -> TelemetrySample:
        return sample._replace(u_depth=applied)

    assert rig.stream(5, far_from_last) == 5
    first = rig.vehicle.commands[before][1]
    assert abs(first.u_depth - applied) <= RATE + WIRE, (first, applied)


@pytest.mark.wire
def test_owner_limits_refuse_setpoints_and_never_clip(make_rig):
    rig = make_rig(
        "--stale-timeout", "30", "--min-depth", "5", "--max-depth", "30", "--max-pitch", "0.3"
    )  # fmt: skip
    assert rig.stream(1) == 0  # the vehicle exists: health is published from now on
    refused = [
        ("depth", 40.0, "depth setpoint 40 m below the maximum depth 30 m"),
        ("depth", 2.0, "depth setpoint 2 m above the minimum depth 5 m"),
        ("pitch", 0.5, "pitch setpoint 0.5 rad beyond ±0.3 rad"),
        ("pitch", -0.5, "pitch setpoint -0.5 rad beyond ±0.3 rad"),
    ]
    for n, (channel, value, why) in enumerate(refused, start=1):
        rig.probe.put(f"glider/1/setpoint/{channel}", {"value": value})
        health = rig.wait_health(lambda h, n=n: h["service_wide"]["setpoints_rejected"] == n)
        assert health["last_rejected_input"] == f"glider/1/setpoint/{channel}: refused: {why}"
        # Refused, not clipped to the limit: no setpoint is in force.
        assert health["control"]["setpoints"] == {"depth": None, "pitch": None}

    assert rig.stream(BLOCKED + 20) == 0
    health = rig.settle()
    assert health["control"]["reason"] == "no setpoint"
    assert health["identifier"]["depth"]["converged"] is True  # only the limits held it

    rig.set_setpoints(30.0, -0.3)  # on the limits: accepted
    rig.wait_health(lambda h: h["control"]["setpoints"] == {"depth": 30.0, "pitch": -0.3})
    assert rig.stream(20) == 20
    assert rig.settle()["service_wide"]["setpoints_rejected"] == len(refused)


# ---- in process: the finer cases ---------------------------------------------------------
class SentFrames:
    """The service's link to a loopback socket of ours; ``frames`` reads what arrived."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.link = Link(f"udpout:127.0.0.1:{self.sock.getsockname()[1]}")
        self._frames: list[bytes] = []

    @property
    def frames(self) -> list[bytes]:
        while True:
            try:
                self._frames.append(self.sock.recv(65536))
            except BlockingIOError:
                return self._frames

    def close(self) -> None:
        self.link.close()
        self.sock.close()


@pytest.fixture
def in_process():
    links: list[SentFrames] = []

    def make(settings: PipelineSettings, inbox: Inbox | None = None):
        link = SentFrames()
        links.append(link)
        config = ServiceConfig(control_default=True, pipeline=settings)
        return HilService(config, Listener(), inbox or Inbox(), link=link.link), link

    yield make
    for link in links:
        link.close()


def commands_in(frames: list[bytes]) -> list[BallastCommand]:
    codec = MavlinkCodec(1, 1)
    return [
        MAPPING.parse_ballast_command(m)
        for frame in frames
        for m in codec.parse(frame, datagram=True)
        if is_ballast_command(m)
    ]


def plant_samples(n: int, seed: int = 1, trim_depth: float = 15.0):
    vehicle_codec = MavlinkCodec(1, 1)
    plant = GliderPlant(PlantConfig(scenario="paper", seed=seed, trim_depth=trim_depth))
    excitation = [RandomSteps(1.5, 5, 20, seed=seed + i) for i in range(2)]
    for k in range(n):
        sample = plant.step(excitation[0].value(k), excitation[1].value(k))
        yield sample, [vehicle_codec.pack(m) for m in MAPPING.encode_telemetry(sample)]


def feed(service: HilService, link: SentFrames, frames: list[bytes]) -> int:
    """Process one sample's datagrams; return the commands it sent."""
    before = len(link.frames)
    for frame in frames:
        service.process_datagram(frame)
    return len(commands_in(link.frames[before:]))


def test_a_command_only_once_recent_skill_reaches_the_minimum(in_process):
    """min_skill above what the identifier reaches at the end of the burn-in: the gate
    opens later, at the first sample whose recent skill reaches it, and not before."""
    min_skill = 0.9  # this identifier is at ~0.80 at the end of the burn-in, 0.9 near k=170
    service, link = in_process(PipelineSettings(burn_in=BURN_IN, min_skill=min_skill))
    service.inbox.set_setpoint(1, "depth", 16.0)
    first = None
    skills = []
    for k, (_, frames) in enumerate(plant_samples(600)):
        sent = feed(service, link, frames)
        skill = service.vehicles[1].pipeline.channels["depth"].stats.recent_skill()
        skills.append(skill)
        if sent and first is None:
            first = k
            assert skill is not None and skill >= min_skill
        if first is None:
            assert not sent
    assert first is not None, "the identifier never reached the minimum skill"
    assert first > BLOCKED + 20, "skill reached the minimum at once: test too weak"
    assert skills[first - 1] < min_skill
    # Once converged it stays so on this data: one command per sample.
    assert len(commands_in(link.frames)) == 600 - first


def _first_commanded(in_process, min_skill: float) -> tuple[int | None, list]:
    service, link = in_process(PipelineSettings(burn_in=BURN_IN, min_skill=min_skill))
    service.inbox.set_setpoint(1, "depth", 16.0)
    skills = []
    for k, (_, frames) in enumerate(plant_samples(600)):
        sent = feed(service, link, frames)
        skills.append(service.vehicles[1].pipeline.channels["depth"].stats.recent_skill())
        if sent:
            return k, skills
    return None, skills


def test_a_recent_skill_exactly_at_the_minimum_opens_the_gate(in_process):
    """The minimum is inclusive: with ``min_skill`` set to the very skill the identifier
    has at the sample where the gate opened for a lower minimum, it opens there too."""
    first, skills = _first_commanded(in_process, 0.5)
    assert first is not None and skills[first] > 0.5
    again, _ = _first_commanded(in_process, skills[first])  # the same data, bit for bit
    assert again == first


def test_commands_start_exactly_after_the_burn_in(in_process):
    service, link = in_process(PipelineSettings(burn_in=BURN_IN))
    service.inbox.set_setpoint(1, "pitch", 0.05)
    sent = [feed(service, link, frames) for _, frames in plant_samples(BLOCKED + 30)]
    assert sent == [0] * BLOCKED + [1] * 30
    pitch_only = commands_in(link.frames)
    assert all(math.isnan(c.u_depth) and math.isfinite(c.u_pitch) for c in pitch_only)


@pytest.mark.parametrize("rate", [0.01, 0.2])
def test_the_rate_limit_caps_every_step(in_process, rate):
    settings = PipelineSettings(burn_in=BURN_IN)
    control = dataclasses.replace(settings.control, rate_limit=rate)
    service, link = in_process(settings.replace(control=control))
    service.inbox.set_setpoint(1, "depth", 18.0)
    service.inbox.set_setpoint(1, "pitch", -0.1)
    samples = []
    for sample, frames in plant_samples(BLOCKED + 300):
        samples.append(sample)
        feed(service, link, frames)
    commands = commands_in(link.frames)
    assert len(commands) == 300
    start = samples[BLOCKED]
    previous = {"depth": start.u_depth, "pitch": start.u_pitch}
    steps = []
    held = {"depth": False, "pitch": False}
    for i, command in enumerate(commands):
        answered = samples[BLOCKED + i]  # one command per sample from here
        for ch, u in (("depth", command.u_depth), ("pitch", command.u_pitch)):
            if not math.isfinite(u):  # not yet qualified by the horizon test: holds
                held[ch] = True
                continue
            if not held[ch]:  # after a hold the step counts from the applied input
                # A re-arm after a supervisor trip takes over from the applied input too
                # (this vehicle ignores commands: the two differ).
                steps.append(min(abs(u - previous[ch]), abs(u - answered.input(ch))))
            held[ch] = False
            previous[ch] = u
    assert not any(held.values()), "a channel never qualified"
    assert max(steps) <= rate + WIRE
    assert max(steps) > rate - WIRE  # it bound


@pytest.mark.parametrize(
    ("channel", "value", "accepted"),
    [
        ("depth", 30.0, True),
        ("depth", 30.001, False),
        ("depth", 5.0, True),
        ("depth", 4.999, False),
        ("pitch", 0.3, True),
        ("pitch", -0.3, True),
        ("pitch", 0.3001, False),
        ("pitch", -0.3001, False),
        ("depth", math.inf, False),
        ("pitch", math.nan, False),
        ("depth", None, True),
    ],
)
def test_owner_limits_at_their_boundaries(channel, value, accepted):
    inbox = Inbox(SetpointLimits(min_depth=5.0, max_depth=30.0, max_abs_pitch=0.3))
    raw = b'{"value": %s}' % (b"null" if value is None else repr(value).encode())
    if value is not None and not math.isfinite(value):
        raw = b'{"value": %s}' % (b"Infinity" if value > 0 else b"NaN")
    inbox.accept(f"glider/1/setpoint/{channel}", raw)
    assert inbox.rejected == (0 if accepted else 1), inbox.last_rejection
    in_force = inbox.get(1).setpoints[channel]
    assert in_force == (value if accepted else None)


def test_limits_on_one_channel_do_not_apply_to_the_other():
    limits = SetpointLimits(min_depth=5.0, max_depth=30.0, max_abs_pitch=0.3)
    assert limits.violation("depth", 0.5) != ""  # a pitch-sized depth is below the minimum
    assert limits.violation("pitch", 20.0) != ""
    assert limits.violation("pitch", 4.0) != ""
    assert SetpointLimits(max_abs_pitch=0.3).violation("depth", 500.0) == ""
    assert SetpointLimits(max_depth=30.0).violation("pitch", 2.0) == ""


def test_no_command_while_the_identifier_resynchronises_after_a_gap(in_process):
    """Five steps lost after convergence: the samples that only refill the model's lags
    are not commanded, though the identifier stays converged (the last of the HISTORY
    refilling samples completes the lags, so it may be, as at the start: BLOCKED)."""
    service, link = in_process(PipelineSettings(burn_in=BURN_IN))
    # Pitch: its model passes the horizon test at the burn-in (depth's later).
    service.inbox.set_setpoint(1, "pitch", 0.05)
    lost = range(BLOCKED + 20, BLOCKED + 25)
    sent, reasons = [], []
    for k, (_, frames) in enumerate(plant_samples(BLOCKED + 60)):
        if k in lost:
            continue
        sent.append(feed(service, link, frames))
        reasons.append(service.vehicles[1].control_reason)
    after = BLOCKED + 20
    assert sent[:after] == [0] * BLOCKED + [1] * 20
    refill = HISTORY - 1
    assert sent[after : after + refill] == [0] * refill
    assert set(reasons[after : after + refill]) == {
        "identifier resynchronising after a telemetry gap (pitch)"
    }
    assert sent[after + refill :] == [1] * (len(sent) - after - refill)
    assert service.vehicles[1].pipeline.channels["pitch"].converged


def test_the_diverging_sample_is_not_commanded_nor_those_after_it(in_process):
    """In process, the forced divergence of the wire test: the sample that trips the
    divergence test gets no command and says so; then the skill must come back. Only the
    diverged channel is held: with both setpoints, a depth-only divergence leaves the
    pitch commands going (NaN for depth: the vehicle keeps its depth input)."""
    service, link = in_process(PipelineSettings(burn_in=BURN_IN))
    service.inbox.set_setpoint(1, "depth", 1.0)
    codec = MavlinkCodec(1, 2)
    sent, reasons = [], []
    # This plant ignores the commands (its own excitation drives it), so the supervisor
    # may trip first; the divergence test is on the identifier either way.
    burst = range(BLOCKED + 40, BLOCKED + 50)
    for k, (sample, frames) in enumerate(plant_samples(BLOCKED + 90, trim_depth=0.5)):
        if k in burst:
            depth = 10_000.0 if (k - burst.start) % 2 == 0 else 0.0
            edited = sample._replace(depth=depth)
            frames = [codec.pack(m) for m in MAPPING.encode_telemetry(edited)]
        before = len(link.frames)
        sent.append(feed(service, link, frames))
        reasons.append(service.vehicles[1].control_reason)
        tripped_now = service.vehicles[1].pipeline.channels["depth"].tripped
        if sent[-1] and k >= burst.stop - 1:  # only a tripped channel's safe input
            assert tripped_now, k
            assert [c.u_depth for c in commands_in(link.frames[before:])] == [0.0]
        if k == burst.stop - 1:  # what health says of the identifier at the tripping sample
            tripped = service.vehicles[1].pipeline.identifier_health()["depth"]
    assert sent[BLOCKED : burst.start] == [1] * 40
    assert sent[burst.start : burst.stop - 1] == [1] * 9
    assert reasons[burst.stop - 1].startswith("identifier diverged (depth)")
    assert tripped["divergences"] == 1 and tripped["converged"] is False
    assert all(r.startswith("identifier not converged (depth:") for r in reasons[burst.stop :])


def test_the_identifier_gate_holds_one_channel_not_the_vehicle():
    """The same divergence with both setpoints, on a plant that follows the commands:
    depth's identifier gate holds depth (NaN, named in the reason) while pitch's commands
    go on, sample after sample."""
    from hil_service.pipeline import VehiclePipeline

    pipeline = VehiclePipeline(PipelineSettings(burn_in=BURN_IN))
    plant = GliderPlant(PlantConfig(scenario="paper", seed=1, trim_depth=0.5))
    excitation = [RandomSteps(1.5, 5, 20, seed=1 + i) for i in range(2)]
    setpoints = {"depth": 1.0, "pitch": 0.05}
    burst = range(BLOCKED + 40, BLOCKED + 50)
    decisions = []
    command = (0.0, 0.0)
    for k in range(BLOCKED + 90):
        sample = plant.step(*command)
        if k in burst:
            sample = sample._replace(depth=10_000.0 if (k - burst.start) % 2 == 0 else 0.0)
        pipeline.observe(sample)
        decision = pipeline.decide(sample, setpoints, True)
        decisions.append(decision)
        if k < BLOCKED:
            command = (excitation[0].value(k), excitation[1].value(k))
        elif decision.command is not None:
            command = (decision.command.u_depth, decision.command.u_pitch)
    assert not pipeline.channels["pitch"].tripped
    after = decisions[burst.stop - 1 :]
    assert not pipeline.channels["depth"].converged
    assert all(d.command is not None for d in after)
    assert all(math.isfinite(d.command.u_pitch) for d in after)
    assert all(d.payload["mode"].split("/")[1] in ("newton", "fallback") for d in after)
    # Depth holds (NaN) or, if its supervisor caught the burst first, sends its safe input.
    depth = pipeline.channels["depth"]
    for d in after:
        path = d.payload["mode"].split("/")[0]
        assert (path == "-" and math.isnan(d.command.u_depth)) or (
            path == "safe" and depth.tripped and d.command.u_depth == depth.safe_u
        ), d.payload
    assert after[0].reason.startswith("identifier diverged (depth)")
    assert all(d.reason.startswith("identifier not converged (depth:") for d in after[1:])
    # The identifier's gate holds depth alone: pitch goes on commanding.
    assert all(d.command is not None for d in decisions[BLOCKED : burst.start])


def test_the_horizon_test_qualifies_while_control_is_off():
    """The horizon test runs on the observing side: health's ``horizon_qualified`` turns
    true on identification data alone, control never enabled."""
    from hil_service.pipeline import VehiclePipeline

    pipeline = VehiclePipeline(PipelineSettings(burn_in=BURN_IN))
    qualified = []
    for sample, _ in plant_samples(BLOCKED + 600):
        pipeline.observe(sample)
        qualified.append(pipeline.identifier_health()["pitch"]["horizon_qualified"])
    assert not qualified[0] and qualified[-1], "pitch never qualified with control off"
    assert not any(p.active for p in pipeline.channels.values())


def test_samples_the_identifier_rejects_never_count_toward_convergence():
    """The assembler drops non-finite telemetry, but the pipeline guards too: a sample the
    identifier rejects is counted as rejected, not as a perfect prediction in the skill."""
    from hil_service.pipeline import VehiclePipeline

    pipeline = VehiclePipeline(PipelineSettings(burn_in=BURN_IN))
    samples = [sample for sample, _ in plant_samples(BLOCKED + 5)]
    for sample in samples[:BLOCKED]:
        pipeline.observe(sample)
    depth = pipeline.channels["depth"]
    counted, skill = depth.stats.count, depth.stats.recent_skill()
    for sample in samples[BLOCKED:]:
        pipeline.observe(sample._replace(depth=math.nan))
    assert depth.rejected == 5
    assert (depth.stats.count, depth.stats.recent_skill()) == (counted, skill)
    decision = pipeline.decide(samples[-1], {"depth": 16.0, "pitch": None}, True)
    assert decision.command is None
    assert decision.reason.startswith(f"identifier not converged (depth: {BURN_IN - 1}/")


def test_disabled_and_no_setpoint_are_named_and_send_nothing_in_process():
    from hil_service.pipeline import VehiclePipeline

    pipeline = VehiclePipeline(PipelineSettings(burn_in=BURN_IN))
    samples = [sample for sample, _ in plant_samples(BLOCKED + 1)]
    for sample in samples:
        pipeline.observe(sample)
    last = samples[-1]
    on = pipeline.decide(last, {"depth": None, "pitch": 0.05}, True)
    assert on.command is not None and on.reason == ""  # converged: the gate is open
    # The channel without a setpoint is left unchanged: NaN on the wire, null on Zenoh.
    assert math.isnan(on.command.u_depth) and math.isfinite(on.command.u_pitch)
    assert on.payload["u_depth"] is None and on.payload["u_pitch"] == on.command.u_pitch
    assert on.payload["mode"].startswith("-/")
    cases = [
        ({"depth": 16.0, "pitch": 0.0}, False, "control disabled"),
        ({"depth": None, "pitch": None}, True, "no setpoint"),
        ({"depth": math.nan, "pitch": math.inf}, True, "no setpoint"),
    ]
    for setpoints, enabled, reason in cases:
        decision = pipeline.decide(last, setpoints, enabled)
        assert (decision.command, decision.payload, decision.reason) == (None, None, reason)


def test_a_rejected_reading_right_after_a_gap_leaves_control_on_the_relearnt_history():
    """After a gap the multi-step map kept for control held pre-gap histories and is
    dropped; if the first sample learnt from after the refill is one the identifier
    rejects (an output beyond its limit), control goes on from the model's current map."""
    from hil_service.pipeline import VehiclePipeline

    pipeline = VehiclePipeline(PipelineSettings(burn_in=BURN_IN))
    depth = pipeline.channels["depth"]
    # Long enough for depth's model to pass the horizon test before the gap.
    samples = [sample for sample, _ in plant_samples(BLOCKED + 235 + HISTORY + 1)]
    lost = range(BLOCKED + 230, BLOCKED + 235)
    kept = [s for k, s in enumerate(samples) if k not in lost]
    for sample in kept[:-1]:
        pipeline.observe(sample)
    assert depth.converged and depth.resync == 0
    assert pipeline.decide(kept[-2], {"depth": 16.0, "pitch": None}, True).reason == ""
    wild = kept[-1]._replace(depth=1e12)
    assert pipeline.observe(wild)["depth"]["status"] == "rejected"
    decision = pipeline.decide(wild, {"depth": 16.0, "pitch": None}, True)
    assert decision.reason == "" and decision.command is not None
    assert math.isfinite(decision.command.u_depth)


def test_each_divergence_is_counted():
    """Health's ``divergences`` counts every divergence, not only whether there was one:
    two bursts of wild readings, far apart, are two divergences."""
    from hil_service.pipeline import VehiclePipeline

    pipeline = VehiclePipeline(PipelineSettings(burn_in=BURN_IN))
    first, second = range(BLOCKED + 20, BLOCKED + 30), range(BLOCKED + 80, BLOCKED + 90)
    counts = []
    for k, (sample, _) in enumerate(plant_samples(BLOCKED + 100, trim_depth=0.5)):
        if k in first or k in second:
            start = first.start if k in first else second.start
            sample = sample._replace(depth=10_000.0 if (k - start) % 2 == 0 else 0.0)
        pipeline.observe(sample)
        counts.append(pipeline.identifier_health()["depth"]["divergences"])
    assert counts[first.start] == 0 and counts[second.start - 1] == 1
    assert counts[-1] == 2
