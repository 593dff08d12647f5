"""Control inputs from the operators (setpoints, control on/off) and the owner's limits.

Zenoh callbacks write an ``Inbox``; the MAVLink thread reads it once per sample. Setpoints
outside the owner's ``SetpointLimits`` are refused (counted and named), never clipped.
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, field

from protocols import keys
from protocols.payload_json import is_finite_number
from protocols.samples import TelemetrySample
from protocols.schemas import validation_errors


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


#: The flag that sets each limit, to name it in an error.
_LIMIT_FLAGS = {
    "min_depth": "--min-depth",
    "max_depth": "--max-depth",
    "max_abs_pitch": "--max-pitch",
}


@dataclass(frozen=True)
class SetpointLimits:
    """Limits a vehicle owner sets: setpoints outside them are refused, never clipped.

    A limit that would refuse nothing or everything unnoticed is itself refused (ValueError
    naming the flag): a non-finite one (every comparison with NaN is false), a negative
    largest |pitch|, a minimum depth deeper than the maximum. ``min_depth == max_depth`` is taken:
    it is a consistent range that admits one depth, e.g. to hold a vehicle at one level.
    """

    min_depth: float | None = None  # m
    max_depth: float | None = None  # m
    max_abs_pitch: float | None = None  # rad

    def __post_init__(self) -> None:
        for name, flag in _LIMIT_FLAGS.items():
            value = getattr(self, name)
            if value is not None and not is_finite_number(value):
                raise ValueError(f"{flag} must be a finite number, got {value!r}")
        if self.max_abs_pitch is not None and self.max_abs_pitch < 0:
            raise ValueError(
                f"--max-pitch is the largest |pitch|: it must be ≥ 0 rad, got "
                f"{self.max_abs_pitch:g}"
            )
        if (
            self.min_depth is not None
            and self.max_depth is not None
            and self.min_depth > self.max_depth
        ):
            raise ValueError(
                f"--min-depth {self.min_depth:g} m is deeper than --max-depth "
                f"{self.max_depth:g} m: every depth setpoint would be refused"
            )

    def violation(self, channel: str, value: float) -> str:
        """Why ``value`` is refused for ``channel``, or "" when it is acceptable."""
        if not math.isfinite(value):
            return f"{channel} setpoint {value} is not a finite number"
        if channel == "depth":
            if self.max_depth is not None and value > self.max_depth:
                return f"depth setpoint {value:g} m below the maximum depth {self.max_depth:g} m"
            if self.min_depth is not None and value < self.min_depth:
                return f"depth setpoint {value:g} m above the minimum depth {self.min_depth:g} m"
        elif self.max_abs_pitch is not None and abs(value) > self.max_abs_pitch:
            return f"pitch setpoint {value:g} rad beyond ±{self.max_abs_pitch:g} rad"
        return ""


#: The largest integer every float holds exactly. A JSON setpoint may be an integer of any
#: size; beyond this one it is no depth or pitch, and the log's encoder (64-bit integers)
#: could not write it.
MAX_EXACT_INTEGER = 2**53
#: The longest refusal reason kept: health repeats the last one every second for every
#: vehicle, and a reason may quote the refused input.
MAX_REASON = 300


def _shortened(reason: str) -> str:
    """``reason``, cut to ``MAX_REASON`` characters with the length it had."""
    if len(reason) <= MAX_REASON:
        return reason
    return f"{reason[:MAX_REASON]}… ({len(reason):,} characters)"


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

    def accept(self, key: str, raw: bytes) -> str:
        """Parse one received setpoint/control message; bad ones are counted, never raised.

        Returns why it was refused, or "" when it was taken: the recorder keeps accepted
        inputs on their own channel and refused ones, with this reason, apart.
        """
        reason = _shortened(self._apply(key, raw))
        if reason:
            self.reject(reason)
        return reason

    def _apply(self, key: str, raw: bytes) -> str:
        """Take the input if it is valid; otherwise why not (nothing changed then)."""
        parsed = keys.parse(key)
        if parsed is None or parsed.kind not in (keys.SETPOINT, keys.CONTROL):
            return f"{key}: not a setpoint or control key"
        try:
            payload = json.loads(raw)
        except ValueError as error:
            return f"{key}: {error}"
        except RecursionError:
            return f"{key}: JSON nested too deeply"
        errors = validation_errors(keys.SCHEMA_FOR_KIND[parsed.kind], payload)
        if errors:
            return f"{key}: {errors[0]}"
        if parsed.channel is not None:  # a setpoint
            value = payload["value"]
            if isinstance(value, int) and abs(value) > MAX_EXACT_INTEGER:
                return f"{key}: setpoint integer beyond ±2**53 (no float holds it exactly)"
            if value is not None and not math.isfinite(value):
                return f"{key}: non-finite setpoint"
            violation = "" if value is None else self.limits.violation(parsed.channel, value)
            if violation:
                return f"{key}: refused: {violation}"
            self.set_setpoint(parsed.system_id, parsed.channel, value)
        else:
            self.set_enabled(parsed.system_id, bool(payload["enabled"]))
        return ""
