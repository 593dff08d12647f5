"""What `serve --profile ardusub` will do, in-process, on a real UDP socket: a companion on
the vehicle's system id and component 191 (heartbeat, stream requests), periodic samples
from the vehicle's streams, optionally the identification/control pipeline, and ballast
commands as the profile sends them (DO_SET_SERVO per channel)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from hil_service.pipeline import PipelineSettings, VehiclePipeline
from hil_service.sources.companion import COMPANION_COMPONENT, Companion
from hil_service.sources.periodic_assembler import ProfileAssembler
from protocols.profiles import Profile
from tests.mavlink_peer import UdpPeer


@dataclass
class Trace:
    t: list[float] = field(default_factory=list)
    depth: list[float] = field(default_factory=list)
    pitch: list[float] = field(default_factory=list)
    setpoint: list[dict] = field(default_factory=list)


class ArduSubClient:
    def __init__(
        self,
        profile: Profile,
        period: float,
        pipeline: PipelineSettings | None = None,
        system_id: int = 1,
    ):
        self.profile = profile
        self.system_id = system_id
        self.peer = UdpPeer(system_id=system_id, component_id=COMPANION_COMPONENT)
        self.companion = Companion(profile, period, target_system=system_id)
        self.assembler = ProfileAssembler(profile, period)
        self.pipeline = VehiclePipeline(pipeline) if pipeline is not None else None
        self.setpoints: dict[str, float | None] = {"depth": None, "pitch": None}
        self.samples = []
        self.acks = []
        self.servo_usec = []
        self.commands_sent = 0
        self.decisions_blocked: dict[str, int] = {}
        self.trace = Trace()

    @property
    def port(self) -> int:
        return self.peer.port

    def close(self) -> None:
        self.peer.close()

    def run(self, seconds: float, until=None) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            for item in self.peer.receive_until(lambda got: True, 0.05):
                self._message(item.message, item.arrival)
            if self.peer.remote is not None:
                for message in self.companion.poll(time.monotonic()):
                    self.peer.send(message)
            if until is not None and until():
                return

    def _message(self, message, arrival: float) -> None:
        self.companion.on_message(message, arrival)
        kind = message.get_type()
        if kind == "COMMAND_ACK":
            self.acks.append(message)
        elif kind == "SERVO_OUTPUT_RAW":
            self.servo_usec.append(message.time_usec)
        for sample, reused in self.assembler.add_all_flagged(message):
            self.samples.append(sample)
            self._sample(sample, reused)

    def _sample(self, sample, inputs_reused: bool = False) -> None:
        self.trace.t.append(sample.t)
        self.trace.depth.append(sample.depth)
        self.trace.pitch.append(sample.pitch)
        self.trace.setpoint.append(dict(self.setpoints))
        if self.pipeline is None:
            return
        self.pipeline.observe(sample, inputs_reused, sampled=True)
        enabled = any(v is not None for v in self.setpoints.values())
        decision = self.pipeline.decide(sample, self.setpoints, enabled)
        if decision.command is None:
            self.decisions_blocked[decision.reason] = (
                self.decisions_blocked.get(decision.reason, 0) + 1
            )
            return
        for command in self.profile.command_messages(
            decision.command.u_depth, decision.command.u_pitch, self.system_id
        ):
            self.peer.send(command)
            self.commands_sent += 1
