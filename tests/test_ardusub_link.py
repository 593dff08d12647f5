"""The service-side pieces (companion manners, periodic sampling, DO_SET_SERVO commands)
against `glider-hil emulate --profile ardusub` on loopback UDP, across a µs-clock wrap."""

from __future__ import annotations

import itertools
import time

from hil_service.cli.processes import last_json
from hil_service.companion import COMPANION_COMPONENT, Companion
from hil_service.profile_assembler import ProfileAssembler
from protocols.mavlink_io import dialect
from protocols.profiles import load_profile
from tests.mavlink_peer import UdpPeer

SPEED = 5.0
PERIOD = 0.1
US32_SPAN = (1 << 32) / 1e6
PROFILE = load_profile("ardusub")


class Client:
    """What `serve --profile ardusub` will do, in-process: a companion on the vehicle's
    system id, component 191, sampling the vehicle's streams."""

    def __init__(self, peer: UdpPeer):
        self.peer = peer
        self.companion = Companion(PROFILE, PERIOD, target_system=1)
        self.assembler = ProfileAssembler(PROFILE, PERIOD)
        self.samples = []
        self.acks = []
        self.servo_usec = []

    def run(self, seconds: float, until=None) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            for item in self.peer.receive_until(lambda got: True, 0.05):
                message = item.message
                self.companion.on_message(message, item.arrival)
                self.samples += self.assembler.add_all(message)
                if message.get_type() == "COMMAND_ACK":
                    self.acks.append(message)
                if message.get_type() == "SERVO_OUTPUT_RAW":
                    self.servo_usec.append(message.time_usec)
            if self.peer.remote is not None:
                for message in self.companion.poll(time.monotonic()):
                    self.peer.send(message)
            if until is not None and until():
                return


def test_companion_samples_ardusub_streams_and_commands_servos_across_a_wrap(processes):
    peer = UdpPeer(system_id=1, component_id=COMPANION_COMPONENT)
    emulator = processes.start(
        "emulate",
        "--profile",
        "ardusub",
        "--connect",
        f"udpout:127.0.0.1:{peer.port}",
        "--speed",
        str(SPEED),
        "--period",
        str(PERIOD),
        "--uptime",
        f"{US32_SPAN - 20:.3f}",
        "--duration",
        "600",
        "--excitation",
        "prbs",
        "--seed",
        "2",
        "--command-timeout",
        "1000",
    )
    try:
        client = Client(peer)
        # Until every stream runs at the sample rate (the vehicle accepted each request).
        client.run(30.0, lambda: set(client.companion.states.values()) == {"accepted"})
        assert set(client.companion.states.values()) == {"accepted"}
        assert client.companion.counters.acks == {"MAV_RESULT_ACCEPTED": 4}
        # Then 40 simulated seconds, across the wrap of SERVO_OUTPUT_RAW's µs clock.
        client.run(0.5)  # the new rates take effect within a message interval
        first_sample, first_usec = len(client.samples), len(client.servo_usec)
        for command in PROFILE.command_messages(1.0, -0.5, target_system=1):
            peer.send(command)
        client.run(40.0 / SPEED)
        samples = client.samples[first_sample:]
        usec = client.servo_usec[first_usec:]
        assert any(b < a for a, b in itertools.pairwise(usec)), "no µs wrap seen"
        expected = round((samples[-1].t - samples[0].t) / PERIOD) + 1
        ratio = len(samples) / expected
        print(
            f"\nardusub streams: {len(samples)} samples formed of {expected} expected "
            f"({100 * ratio:.1f} %), counters {client.assembler.counters.as_dict()}"
        )
        assert ratio >= 0.95
        times = [s.t for s in samples]
        assert all(b > a for a, b in itertools.pairwise(times))
        # DO_SET_SERVO, one per channel, accepted; the outputs read back what was commanded
        # (1700 µs = 1.0 model units, 1400 µs = −0.5) after the actuator's rate limit.
        servo_acks = [a for a in client.acks if a.command == dialect.MAV_CMD_DO_SET_SERVO]
        assert [a.result for a in servo_acks] == [dialect.MAV_RESULT_ACCEPTED] * 2
        assert abs(samples[-1].u_depth - 1.0) < 0.01 and abs(samples[-1].u_pitch + 0.5) < 0.01
        # The vehicle saw the companion's heartbeats, as an onboard controller's.
        out, _ = processes.stop(emulator)
        heartbeats = last_json(out, "emulator")["gcs"]["heartbeats"]
        assert heartbeats.get("MAV_TYPE_ONBOARD_CONTROLLER", 0) >= 5
    finally:
        peer.close()
