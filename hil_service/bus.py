"""The service's Zenoh side behind a small interface, so replay and benchmarks can swap it.

``ZenohBus`` publishes JSON payloads (commands with congestion control BLOCK, the rest with
DROP), records every publication and every received input to MCAP, and hands received
setpoints and control messages to an ``Inbox`` without blocking Zenoh's callback threads.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import zenoh

from hil_service.recorder import McapRecorder
from protocols import keys, payload_json
from protocols.samples import TelemetrySample
from protocols.schemas import validation_errors


class Bus(Protocol):
    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None: ...

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None: ...

    def close(self) -> None: ...


@dataclass
class ControlInputs:
    """Latest setpoints and control flag for one vehicle, as received."""

    setpoints: dict[str, float | None] = field(
        default_factory=lambda: {"depth": None, "pitch": None}
    )
    enabled: bool | None = None  # None: nothing received, use the configured default
    reset: bool = False  # replay only: controllers were re-armed before this sample


#: What a vehicle with no input received yet is given (never modified).
_NO_INPUTS = ControlInputs()


@dataclass(frozen=True)
class SetpointLimits:
    """Limits a vehicle owner sets: setpoints outside them are refused, never clipped."""

    min_depth: float | None = None  # m
    max_depth: float | None = None  # m
    max_abs_pitch: float | None = None  # rad

    def violation(self, channel: str, value: float) -> str:
        """Why ``value`` is refused for ``channel``, or "" when it is acceptable."""
        if channel == "depth":
            if self.max_depth is not None and value > self.max_depth:
                return f"depth setpoint {value:g} m below the maximum depth {self.max_depth:g} m"
            if self.min_depth is not None and value < self.min_depth:
                return f"depth setpoint {value:g} m above the minimum depth {self.min_depth:g} m"
        elif self.max_abs_pitch is not None and abs(value) > self.max_abs_pitch:
            return f"pitch setpoint {value:g} rad beyond ±{self.max_abs_pitch:g} rad"
        return ""


class Inbox:
    """Thread-safe store of control inputs, written by Zenoh callbacks, read per sample.

    Writers replace a vehicle's ``ControlInputs`` with a new object under the lock and never
    change a published one, so the per-sample read is a plain dictionary lookup.
    """

    def __init__(self, limits: SetpointLimits | None = None) -> None:
        self.limits = limits or SetpointLimits()
        self._lock = threading.Lock()
        self._inputs: dict[int, ControlInputs] = {}
        self.rejected = 0
        self.last_rejection = ""

    def inputs_for(self, sample: TelemetrySample) -> ControlInputs:
        """The inputs in force for ``sample`` (live: the latest received). Read-only."""
        return self._inputs.get(sample.system_id) or _NO_INPUTS

    def get(self, system_id: int) -> ControlInputs:
        """A copy of the latest inputs for ``system_id``, free to change."""
        current = self._inputs.get(system_id) or _NO_INPUTS
        return ControlInputs(dict(current.setpoints), current.enabled)

    def set_setpoint(self, system_id: int, channel: str, value: float | None) -> None:
        with self._lock:
            current = self._inputs.get(system_id) or _NO_INPUTS
            setpoints = {**current.setpoints, channel: value}
            self._inputs[system_id] = ControlInputs(setpoints, current.enabled)

    def set_enabled(self, system_id: int, enabled: bool) -> None:
        with self._lock:
            current = self._inputs.get(system_id) or _NO_INPUTS
            self._inputs[system_id] = ControlInputs(dict(current.setpoints), enabled)

    def reject(self, reason: str) -> None:
        with self._lock:
            self.rejected += 1
            self.last_rejection = reason

    def accept(self, key: str, raw: bytes) -> None:
        """Parse one received setpoint/control message; bad ones are counted, never raised."""
        parts = key.split("/")
        try:
            system_id = int(parts[1])
            payload = json.loads(raw)
        except (IndexError, ValueError) as error:
            self.reject(f"{key}: {error}")
            return
        kind = parts[2] if len(parts) > 2 else ""
        schema = "setpoint" if kind == "setpoint" else "control"
        errors = validation_errors(schema, payload)
        if errors:
            self.reject(f"{key}: {errors[0]}")
            return
        if kind == "setpoint" and len(parts) == 4 and parts[3] in keys.CHANNELS:
            value = payload["value"]
            if value is not None and not math.isfinite(value):
                self.reject(f"{key}: non-finite setpoint")
                return
            violation = "" if value is None else self.limits.violation(parts[3], value)
            if violation:
                self.reject(f"{key}: refused: {violation}")
                return
            self.set_setpoint(system_id, parts[3], value)
        elif kind == "control" and len(parts) == 3:
            self.set_enabled(system_id, bool(payload["enabled"]))
        else:
            self.reject(f"{key}: not a setpoint or control key")


class NullBus:
    """Publishes nothing: replay without ``--publish``, benchmarks of the decode path."""

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        pass

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        pass

    def close(self) -> None:
        pass


class ZenohBus:
    def __init__(
        self,
        session: zenoh.Session,
        inbox: Inbox,
        recorder: McapRecorder | None = None,
    ):
        self.session = session
        self.inbox = inbox
        self.recorder = recorder
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._declared: dict[int, list[Any]] = {}
        self._subscribers: list[Any] = [
            session.declare_subscriber(f"{keys.ROOT}/*/setpoint/*", self._on_input),
            session.declare_subscriber(f"{keys.ROOT}/*/control", self._on_input),
        ]

    def _on_input(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: parse and store only, never block.
        key = str(sample.key_expr)
        raw = sample.payload.to_bytes()
        if self.recorder is not None:
            try:
                payload: Any = json.loads(raw)
            except ValueError:
                payload = {"raw": raw.decode("utf-8", "replace")}
            self.recorder.zenoh(key, payload, "in")
        self.inbox.accept(key, raw)

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        publisher = self._publishers.get(key)
        if publisher is None:
            congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
            publisher = self.session.declare_publisher(
                key, congestion_control=congestion, encoding=zenoh.Encoding.APPLICATION_JSON
            )
            self._publishers[key] = publisher
        data = payload_json.encode(payload)
        publisher.put(data)
        if self.recorder is not None:
            self.recorder.zenoh_encoded(key, data, "out")

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        """Liveliness token and state queryable for a newly seen vehicle."""
        if system_id in self._declared:
            return

        def answer(query: zenoh.Query) -> None:
            query.reply(keys.state(system_id), payload_json.encode(state()))

        self._declared[system_id] = [
            self.session.liveliness().declare_token(keys.service(system_id)),
            self.session.declare_queryable(keys.state(system_id), answer),
        ]

    def close(self) -> None:
        for declared in [*self._subscribers, *self._publishers.values()]:
            declared.undeclare()
        for items in self._declared.values():
            for item in items:
                item.undeclare()
        self._publishers.clear()
        self._declared.clear()
