"""The HIL service runtime: MAVLink in, identification and control, Zenoh out, MCAP always.

One thread owns the MAVLink link and everything on the per-sample path (decode, assemble,
identify, decide, publish, send). Samples come from the profile's ``SampleSource``
(``hil_service.sources``: lockstep or periodic); everything that consumes the stream (the
log, Zenoh, the live view, replay's collector) is a listener of one ``Notifier``
(``hil_service.listeners``). Zenoh callbacks only fill the ``Inbox``; the recorder writes on
its own thread. ``process_datagram`` is the same entry point for live traffic, replay and
benchmarks.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.link_stats import RateMeter, SequenceTracker
from hil_service.listeners import Listener, Notifier
from hil_service.mcap.recorder import McapRecorder
from hil_service.pipeline import VehiclePipeline, choice_spread
from hil_service.sources import SampleSource, source_for
from hil_service.sources.companion import ack_is_ours
from hil_service.vehicle_links import LinkIdentity, LinkSet, identity_for
from protocols import keys
from protocols.mapping import MSG_ACK, SERVICE_COMPONENT, ack_accepted
from protocols.mavlink_io import (
    Address,
    Link,
    MavlinkCodec,
    MavMessage,
    header_of,
    system_of,
    type_of,
)
from protocols.samples import TelemetrySample

#: Whether commands and supervisor events go with congestion control BLOCK
#: (``keys.RELIABLE_KINDS``).
COMMANDS_RELIABLE = keys.COMMAND_BALLAST in keys.RELIABLE_KINDS
EVENTS_RELIABLE = keys.SUPERVISOR in keys.RELIABLE_KINDS

#: The longest a companion's due message (heartbeat, stream request) waits for a tick, s.
COMPANION_POLL = 0.01


@dataclass
class VehicleRuntime:
    """What the runtime keeps per vehicle beside its pure pipeline."""

    pipeline: VehiclePipeline
    keys: keys.VehicleKeys
    rate: RateMeter = field(default_factory=RateMeter)
    last_sample_wall: float | None = None
    last_sample: TelemetrySample | None = None
    last_estimates: dict[str, dict[str, Any]] = field(default_factory=dict)
    last_command: dict[str, Any] | None = None
    control_reason: str = "no sample yet"
    commands_sent: int = 0
    command_frames: int = 0  # the MAVLink commands they took (a profile may send several)
    #: Its acknowledgements of ballast commands: ``unsolicited`` when there are more than
    #: the commands it was sent (docs/mavlink.md, "Whose message is it").
    acks: dict[str, int] = field(
        default_factory=lambda: {"accepted": 0, "refused": 0, "not_ours": 0, "unsolicited": 0}
    )
    last_applied: dict[str, Any] | None = None
    reset_pending: bool = False


class HilService:
    def __init__(
        self,
        config: ServiceConfig,
        notifier: Notifier | Listener,
        inbox: Inbox,
        link: Link | LinkSet | None = None,
        recorder: McapRecorder | None = None,
        clock: Callable[[], float] = time.monotonic,
        send_commands: bool = True,
    ):
        self.config = config
        #: Every consumer of the stream. A single listener is given a notifier of its own;
        #: ``recorder``, when given, is one of the listeners (and reports in health).
        self.notifier = notifier if isinstance(notifier, Notifier) else Notifier([notifier])
        if recorder is not None and recorder not in self.notifier.listeners:
            self.notifier.add_listener(recorder)
        self.inbox = inbox
        self.link = link
        self.recorder = recorder
        self.profile = config.vehicle_profile()
        #: Over how many samples the vehicles' structure choices spread (their phases mod it).
        self._choice_spread = choice_spread(config.vehicle_slots)
        self.clock = clock
        self.send_commands = send_commands and link is not None
        #: What a datagram makes the service send goes out before the listeners hear of the
        #: datagram (``Notifier.hold``) when the link spins: the vehicle is then on a core
        #: of its own, and works on its next step while the service logs this one.
        self.answer_first = link is not None and link.spin_wait > 0.0
        #: What the service sends to a vehicle is framed as that vehicle's companion (its
        #: system id, component 191), one codec (sequence, signing stream) per vehicle.
        self._senders: dict[int, MavlinkCodec] = {}
        #: Where each vehicle's frames last came from (udpin): its replies go there.
        self._routes: dict[int, Address] = {}
        #: The address each (system, component) was last heard from, and per system how
        #: often one of its components moved to another address: two hosts sending as
        #: one system id alternate on every frame (docs/mavlink.md, "Whose message is it").
        self._heard_from: dict[int, Address] = {}
        self.address_changes: dict[int, int] = {}
        #: ``--vehicle-ids link``: messages renumbered to vehicle ids (vehicle_links.py).
        self.identity: LinkIdentity | None = identity_for(config.vehicle_ids)
        # Decoding (and checking signatures) only: nothing is sent under this identity.
        self.codec = MavlinkCodec.for_link(
            config.service_system_id,
            SERVICE_COMPONENT,
            config.security.key,
            accept_unsigned=config.security.accept_unsigned,
        )
        self.verifier = self.codec.verifier
        #: Where samples come from, as the profile says (lockstep or periodic); what it
        #: sends (releases, heartbeats, stream requests) goes out as the vehicle's companion.
        self.source: SampleSource = source_for(
            config, self._send if self.send_commands else None, clock
        )
        #: Each served vehicle's companion (the source's).
        self.companions = self.source.companions
        self.sequence = SequenceTracker()
        self.vehicles: dict[int, VehicleRuntime] = {}
        self._next_health = 0.0
        self._next_poll = 0.0  # when the companions are polled next (tick)
        self._health_turn = 0  # the next vehicle (in order of first sample) whose health is due
        self._lock = threading.Lock()  # guards snapshots read by the state queryable
        #: More counters of the service as a whole for health's ``service_wide``: the Zenoh
        #: publisher's (vehicles another service serves too) and, when one runs, the live
        #: view's (``LiveView.counters``); builder.wire adds them.
        self.wide_counters: list[Callable[[], dict[str, int]]] = []

    # ---- the per-datagram path --------------------------------------------------------
    def process_datagram(
        self, data: bytes, datagram: bool = True, source: Address = None
    ) -> list[TelemetrySample]:
        """``source``: the address the datagram came from (``Link.recv_from``), where what
        the service sends to the systems in it goes (None: the link's peer)."""
        now_ns = time.time_ns()
        samples = []
        messages = self.codec.parse(data, datagram=datagram)
        notifier = self.notifier
        if self.answer_first:
            notifier.hold()
        try:
            # Refused frames are kept apart: replaying mavlink/raw/in must see what we saw.
            for frame in self.codec.last_rejected:
                notifier.mavlink("rejected", None, frame, now_ns)
            identity = self.identity
            if identity is not None:
                identity.admit(messages, source)
            if source is not None:
                for message in messages:
                    self._heard(header_of(message), source)
            for message in messages:
                notifier.mavlink("in", message, None, now_ns)
                samples.extend(self.process_message(message))
        finally:
            notifier.release()
        return samples

    def _heard(self, header: Any, source: Address) -> None:
        """Commands to a system go where it was last heard from; a component of it heard
        from another address than before is counted."""
        system = header.srcSystem
        self._routes[system] = source
        component = system * 256 + header.srcComponent
        before = self._heard_from.get(component)
        if before != source:
            if before is not None:
                self.address_changes[system] = self.address_changes.get(system, 0) + 1
            self._heard_from[component] = source

    def process_message(self, message: MavMessage) -> list[TelemetrySample]:
        """One decoded message: the samples it completes (a periodic source may complete
        several after a gap), each identified, decided and commanded."""
        header = header_of(message)
        self.sequence.observe(header.srcSystem, header.srcComponent, header.seq)
        flagged = self.source.take(message)
        if type_of(message) == MSG_ACK:
            if self.source.is_command_ack(message):
                self._on_ack(message)
            return []
        if not flagged:
            return []
        for sample, inputs_reused in flagged:
            self.process_sample(sample, inputs_reused)
        return [sample for sample, _ in flagged]

    def process_sample(self, sample: TelemetrySample, inputs_reused: bool = False) -> None:
        vehicle = self._vehicle(sample.system_id)
        now = self.clock()
        vehicle.rate.tick(now)
        vehicle.last_sample_wall = now
        system_id = sample.system_id
        topics = vehicle.keys
        self.notifier.publish(topics.telemetry, sample.to_payload())
        estimates = vehicle.pipeline.observe(sample, inputs_reused, self.source.periodic)
        for channel, payload in estimates.items():
            self.notifier.publish(topics.umodel[channel], payload)
        inputs = self.inbox.inputs_for(sample)
        enabled = self.config.control_default if inputs.enabled is None else inputs.enabled
        reset = vehicle.reset_pending or inputs.reset
        if reset:
            vehicle.pipeline.mark_stale()
            vehicle.reset_pending = False
        applied = {"setpoints": inputs.setpoints, "enabled": enabled}
        if applied != vehicle.last_applied or reset:
            # What the decision below used, stamped with the sample: replay applies exactly
            # this at exactly this sample, so recomputed commands match bit for bit.
            vehicle.last_applied = applied
            self.notifier.record(
                topics.decision_inputs,
                {"time_boot_ms": sample.time_boot_ms, **applied, "reset": reset},
                "internal",
            )
        decision = vehicle.pipeline.decide(sample, inputs.setpoints, enabled)
        with self._lock:
            vehicle.last_sample = sample
            vehicle.last_estimates = estimates
            vehicle.control_reason = decision.reason
            if decision.payload is not None:
                vehicle.last_command = decision.payload
        commanded = False
        if decision.command is not None and decision.payload is not None:
            commanded = True
            # The vehicle first: the Zenoh publish blocks (congestion control BLOCK) while a
            # slow subscriber catches up, and must not hold the command back.
            if self.send_commands:
                command = decision.command
                for message in self.profile.command_messages(
                    command.u_depth, command.u_pitch, system_id
                ):
                    self._send(message, system_id)
                    vehicle.command_frames += 1
            self.notifier.publish(
                topics.command_ballast, decision.payload, reliable=COMMANDS_RELIABLE
            )
            vehicle.commands_sent += 1
        for event in vehicle.pipeline.take_events(sample.time_boot_ms):
            # A supervisor's trip or re-arm (docs/control.md): on Zenoh and in the log through
            # the listeners; counted in health's identifier.{channel}.supervisor.
            self.notifier.publish(topics.supervisor, event, reliable=EVENTS_RELIABLE)
        self.source.after_sample(sample, commanded)  # after the command

    def _send(self, message: MavMessage, system_id: int) -> None:
        """``message`` to vehicle ``system_id``, as its companion, where its frames came from."""
        assert self.link is not None
        identity = self.identity
        wire = system_id if identity is None else identity.outgoing(message, system_id)
        codec = self._senders.get(system_id)
        if codec is None:
            codec = MavlinkCodec(wire, SERVICE_COMPONENT, signing_key=self.config.security.key)
            self._senders[system_id] = codec
        frame = codec.pack(message)
        self.link.send_to(frame, self._routes.get(system_id))
        self.notifier.mavlink("out", message, frame, time.time_ns())

    def _on_ack(self, message: MavMessage) -> None:
        vehicle = self.vehicles.get(system_of(message))
        if vehicle is None:
            return
        acks = vehicle.acks
        if not ack_is_ours(message):  # the vehicle's answer to a ground station
            acks["not_ours"] += 1
        elif acks["accepted"] + acks["refused"] >= vehicle.command_frames:
            acks["unsolicited"] += 1  # no command of ours is waiting for it
        else:
            acks["accepted" if ack_accepted(message) else "refused"] += 1

    def _vehicle(self, system_id: int) -> VehicleRuntime:
        vehicle = self.vehicles.get(system_id)
        if vehicle is None:
            # Vehicles in the order they appear take turns for the controllers' periodic
            # work, so that a fleet that started together does not do it on one sample.
            pipeline = VehiclePipeline(
                self.config.pipeline, phase=len(self.vehicles), spread=self._choice_spread
            )
            vehicle = VehicleRuntime(pipeline, keys.VehicleKeys.of(system_id))
            self.vehicles[system_id] = vehicle
            self.source.vehicle_seen(system_id)
            self.notifier.declare_vehicle(system_id, lambda: self.state(system_id))
        return vehicle

    # ---- periodic work ------------------------------------------------------------------
    def tick(self) -> None:
        """Health at ``health_period``; call often (the run loop does every 0.1 s at most)."""
        now = self.clock()
        if self.link is not None and now >= self._next_poll:
            # Every COMPANION_POLL at most, not after every datagram: what the companions
            # send is due on a scale of seconds (heartbeats, stream requests). The source
            # polls only the companions with something due (CompanionSchedule), so a tick
            # costs what is due, not the fleet's size.
            self._next_poll = now + COMPANION_POLL
            for system_id, message in self.source.due(now):
                self._send(message, system_id)
        if now < self._next_health:
            return
        # One vehicle's health at a time, round robin, paced at health_period / vehicles:
        # each vehicle's still comes once a period, but a fleet's health is no longer one
        # burst (50 vehicles' took 2-14 ms) that every sample arriving meanwhile waits for.
        period = self.config.health_period
        order = list(self.vehicles)
        if not order:
            self._next_health = now + period
            return
        pace = period / len(order)
        published = 0
        while now >= self._next_health and published < len(order):
            system_id = order[self._health_turn % len(order)]
            self._health_turn += 1
            published += 1
            self.notifier.publish(self.vehicles[system_id].keys.health, self.health(system_id, now))
            self._next_health += pace
        if now >= self._next_health:  # far behind (or the first time): no catching-up burst
            self._next_health = now + pace

    def health(self, system_id: int, now: float | None = None) -> dict[str, Any]:
        now = self.clock() if now is None else now
        vehicle = self.vehicles[system_id]
        stale = (
            vehicle.last_sample_wall is None
            or now - vehicle.last_sample_wall > self.config.stale_timeout
        )
        inputs = self.inbox.get(system_id)
        enabled = self.config.control_default if inputs.enabled is None else inputs.enabled
        reason = "telemetry stale" if stale else vehicle.control_reason
        if stale:
            vehicle.reset_pending = True  # controllers re-arm before the next decision
        # Everything in "counters", "link", "samples", "packet_loss" and "malformed" is this
        # vehicle's own; what cannot be told apart by vehicle is under "link_wide" (the
        # MAVLink link: garbage, unknown or refused frames, other systems) and
        # "service_wide" (operator inputs, the log).
        assembled = self._assembled(system_id)
        link = self.sequence.for_system(system_id)
        counters = {
            **assembled,
            "commands_sent": vehicle.commands_sent,
            "acks_accepted": vehicle.acks["accepted"],
            "acks_refused": vehicle.acks["refused"],
            "acks_unsolicited": vehicle.acks["unsolicited"],
            "address_changes": self.address_changes.get(system_id, 0),
            "step_gaps": vehicle.pipeline.gaps.gaps,
        }
        malformed = assembled["invalid"] + assembled["out_of_order"] + assembled["incomplete"]
        payload: dict[str, Any] = {
            "t_wall": time.time(),
            "link_rate": vehicle.rate.rate(now),
            "samples": assembled["samples"],
            "packet_loss": link.loss_fraction,
            "malformed": malformed,
            "counters": counters,
            "link": link.as_dict(),
            "link_wide": self._link_wide(),
            "service_wide": self._service_wide(),
            "identifier": vehicle.pipeline.identifier_health(),
            "control": {
                "enabled": enabled,
                "commanding": reason == "",
                "reason": reason,
                "setpoints": inputs.setpoints,
            },
            "telemetry_age": None
            if vehicle.last_sample_wall is None
            else now - vehicle.last_sample_wall,
        }
        payload["signing"] = {
            **self.config.security.to_json(),
            "rejected": 0 if self.verifier is None else self.verifier.counters.rejected,
            "last_rejection": "" if self.verifier is None else self.verifier.last_reason,
        }
        if self.recorder is not None:
            payload["logging"] = self.recorder.report()
        payload.update(self.source.health(system_id))
        if self.inbox.last_rejection:
            payload["last_rejected_input"] = self.inbox.last_rejection
        return payload

    def _link_wide(self) -> dict[str, int]:
        """Counters of the MAVLink link that belong to no one vehicle: frames decoded from
        every system, bytes that were no frame, frames of unknown types or of systems not
        served (and lockstep announcements from them), and (with signing) the verifier's
        counts."""
        counters = {**self.codec.counters.as_dict(), **self.source.link_counters()}
        if self.verifier is not None:
            counters.update(self.verifier.counters.as_dict())
        return counters

    def _service_wide(self) -> dict[str, int]:
        """Counters of the service as a whole: refused operator inputs, log records, vehicles
        another service on the Zenoh network serves too, the live view's messages (with
        ``--foxglove``)."""
        counters = {"setpoints_rejected": self.inbox.rejected}
        if self.recorder is not None:
            counters["log_records"] = self.recorder.status.records
            counters["log_dropped"] = self.recorder.status.dropped
        for more in self.wide_counters:
            counters.update(more())
        return counters

    def state(self, system_id: int) -> dict[str, Any]:
        """Answer of the ``state`` queryable: the latest sample, estimates and command."""
        with self._lock:
            vehicle = self.vehicles[system_id]
            return {
                "telemetry": None
                if vehicle.last_sample is None
                else vehicle.last_sample.to_payload(),
                "umodel": dict(vehicle.last_estimates),
                "command": vehicle.last_command,
                "control_reason": vehicle.control_reason,
            }

    def _assembled(self, system_id: int) -> dict[str, int]:
        """One vehicle's assembly counters (lockstep or periodic, the same names)."""
        return self.source.counters_for(system_id)

    def summary(self) -> dict[str, Any]:
        """Counters and per-vehicle identification scores, printed when the service stops."""
        return {
            **self.source.summary(),
            "companions": {
                str(system_id): {**c.counters.as_dict(), "stream_requests": c.states}
                for system_id, c in self.companions.items()
            },
            "counters": {
                **self.source.totals(),
                **self.codec.counters.as_dict(),
                **({} if self.verifier is None else self.verifier.counters.as_dict()),
            },
            "link": self.sequence.as_dict(),
            "vehicles": {
                str(system_id): {
                    "identifier": vehicle.pipeline.identifier_health(),
                    "commands_sent": vehicle.commands_sent,
                    "acks": dict(vehicle.acks),
                    "address_changes": self.address_changes.get(system_id, 0),
                    "step_gaps": vehicle.pipeline.gaps.gaps,
                    "counters": self._assembled(system_id),
                    "link": self.sequence.for_system(system_id).as_dict(),
                }
                for system_id, vehicle in self.vehicles.items()
            },
        }

    # ---- the loop -------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        assert self.link is not None
        while not stop.is_set():
            if self.link.wait(0.1):
                data, source = self.link.recv_from()
                if data:
                    self.process_datagram(data, self.link.datagram, source)
            self.tick()
