"""Samples from asynchronous streams: one every ``period`` s on the vehicle's clock.

Real autopilots (ArduSub, PX4) send each message on its own stream at its own rate, stamped
when it is sent, so no two messages share a timestamp. This sampler keeps the newest values
of each signal and forms a sample at every multiple of the period on the vehicle's clock,
from the newest value stamped at or before that time. A signal whose newest value is older
than its staleness limit makes the sample *incomplete*: counted with its reason, never
guessed. Pure: no I/O, no wall clock; the caller feeds it readings and their clock stamps.

Clocks, as real vehicles have them:

* ``ms32`` (``time_boot_ms``), ``us32`` (``SERVO_OUTPUT_RAW.time_usec``: wraps every
  71.6 min) and ``us64`` are put on one time line in seconds. A wrapping clock is unwrapped
  to the candidate nearest the newest time seen, so a wrap is a small step forward.
* A message without a stamp (VFR_HUD) takes the newest vehicle time seen.
* Late and out-of-order messages are kept at their own stamp: a sample waits ``delay`` s of
  vehicle time for them, and one later than that can still serve the next sample.
* A step of more than ``jump`` s (a reboot restarts ``time_boot_ms``; an outage jumps ahead;
  a corrupt stamp goes anywhere) is believed only when the next stamp of the same clock
  agrees with it; then a new *segment* starts from nothing, and the samples' time ``t``
  keeps increasing across it. A lone stamp that disagrees is counted as ``discarded``.
* What a segment tells: a confirmed step *back* is a reboot (a clock counting time since
  boot goes back for nothing else), counted in ``reboots``; a step forward is an outage
  (the clock ran on while nothing arrived). Without a wall clock the sampler cannot tell a
  reboot whose new clock has already passed the old one (a vehicle that rebooted seconds
  after booting, or a silence longer than its uptime before the reboot) from an outage:
  that one is counted as an outage.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import NamedTuple

#: Clock kinds: name → (seconds per tick, wrap modulus in ticks, 0 for none).
CLOCKS: dict[str, tuple[float, int]] = {
    "ms32": (1e-3, 1 << 32),
    "us32": (1e-6, 1 << 32),
    "us64": (1e-6, 0),
}
HISTORY = 16  # values kept per signal source
MAX_GAP_SAMPLES = 10_000  # a longer gap is counted in one go, not emitted sample by sample


@dataclass(frozen=True)
class SamplerConfig:
    """``staleness``: per signal, one limit (s) per source, preferred source first."""

    period: float
    staleness: dict[str, tuple[float, ...]]
    optional: frozenset[str] = frozenset()
    delay: float | None = None  # s of vehicle time a sample waits for late messages
    jump: float | None = None  # s; a larger clock step needs confirming (default below)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"sample period must be positive, got {self.period}")
        for name, limits in self.staleness.items():
            if not limits or not all(math.isfinite(x) and x > 0 for x in limits):
                raise ValueError(f"staleness limits of {name} must be positive, got {limits}")

    @property
    def wait(self) -> float:
        return self.period / 2 if self.delay is None else self.delay

    @property
    def jump_limit(self) -> float:
        return max(2.0, 10 * self.period) if self.jump is None else self.jump


class Tick(NamedTuple):
    """One sample time: ``values`` (signal → value) when complete, else ``reason``.

    ``t`` increases across reboots and wraps; ``vehicle_t`` is the vehicle's own clock (s
    since boot) in the current segment.
    """

    t: float
    vehicle_t: float
    values: dict[str, float] | None
    reason: str = ""
    stamps: dict[str, float] | None = None  # signal → vehicle time of the reading used


@dataclass
class SamplerCounters:
    samples: int = 0
    incomplete: int = 0
    reasons: dict[str, int] = field(default_factory=dict)
    fallbacks: dict[str, int] = field(default_factory=dict)
    segments: int = 0  # clock discontinuities believed (reboots, outages)
    reboots: int = 0  # of those, the clock stepping back: the vehicle rebooted
    discarded: int = 0  # stamps that jumped and were not confirmed
    invalid: int = 0  # non-finite values
    unstamped: int = 0  # values without a stamp before any clock was seen
    unknown: int = 0  # readings of a signal the sampler was not told about

    def as_dict(self) -> dict[str, object]:
        return {
            "samples": self.samples,
            "incomplete": self.incomplete,
            "reasons": dict(self.reasons),
            "fallbacks": dict(self.fallbacks),
            "segments": self.segments,
            "reboots": self.reboots,
            "discarded": self.discarded,
            "invalid": self.invalid,
            "unstamped": self.unstamped,
            "unknown": self.unknown,
        }

    def count(self, reason: str, n: int = 1) -> None:
        self.incomplete += n
        self.reasons[reason] = self.reasons.get(reason, 0) + n


class StreamSampler:
    """Periodic samples of one vehicle from readings stamped with its clocks."""

    def __init__(self, config: SamplerConfig):
        self.config = config
        self.counters = SamplerCounters()
        self._frontier: float | None = None  # newest vehicle time seen (s, this segment)
        self._next_k = 0  # index of the next sample in this segment
        self._offset = 0.0  # t = offset + vehicle_t
        self._last_t: float | None = None  # the last tick's t
        self._pending: dict[str, float] = {}  # clock kind → an unconfirmed jump's time
        self._history: dict[tuple[str, int], list[tuple[float, float]]] = {}

    # ---- clocks ------------------------------------------------------------------------
    def _seconds(self, kind: str, raw: int) -> float:
        unit, modulus = CLOCKS[kind]
        t = raw * unit
        if modulus and self._frontier is not None:
            span = modulus * unit
            t += span * round((self._frontier - t) / span)  # the candidate nearest
        return t

    def _stamp(self, clock: tuple[str, int] | None) -> float | None:
        """The vehicle time of a reading, after any segment change it confirms; None to drop."""
        if clock is None:
            return self._frontier
        kind, raw = clock
        if kind not in CLOCKS:
            raise ValueError(f"unknown clock {kind!r}")
        t = self._seconds(kind, raw)
        if self._frontier is None:
            self._start_segment(t)
            return t
        limit = self.config.jump_limit
        if abs(t - self._frontier) <= limit:
            if self._pending.pop(kind, None) is not None:
                self.counters.discarded += 1
            self._frontier = max(self._frontier, t)
            return t
        pending = self._pending.get(kind)
        if pending is not None and abs(t - pending) <= limit:
            self._pending.clear()
            self._new_segment(t)
            return t
        if pending is not None:
            self.counters.discarded += 1
        self._pending[kind] = t
        return None

    def _start_segment(self, t: float) -> None:
        self._frontier = t
        self._next_k = math.ceil(t / self.config.period - 1e-9)
        self._history.clear()
        if self._last_t is not None:
            # Keep t increasing: across a reboot it continues one period after the last
            # tick; across a forward jump it keeps the time that passed.
            first = self._next_k * self.config.period
            self._offset = max(self._offset, self._last_t + self.config.period - first)

    def _new_segment(self, t: float) -> None:
        self.counters.segments += 1
        assert self._frontier is not None
        if t < self._frontier:
            self.counters.reboots += 1
        elif t > self._frontier:  # an outage: the samples it cost are incomplete
            missed = math.floor((t - self._frontier) / self.config.period)
            if missed > 0:
                self.counters.count("clock jump", missed)
        self._start_segment(t)

    # ---- readings ----------------------------------------------------------------------
    def observe(
        self, readings: Iterable[tuple[str, int, float]], clock: tuple[str, int] | None
    ) -> list[Tick]:
        """The values one message carries (signal, source rank, value), stamped by
        ``clock`` (kind, raw) or None; returns the ticks that became due."""
        stamp = self._stamp(clock)
        # A clock tick spans its resolution: a reading stamped ``raw`` was taken in
        # [raw, raw + unit) (the vehicle truncates its clock), so it is placed at the middle.
        # One stamped exactly at a sample time was taken after it, almost surely: with the
        # tick's start, a reading taken just after a loop step (carrying the new state) would
        # serve the sample before it, and the next sample would serve it again.
        taken = stamp
        if stamp is not None and clock is not None:
            taken = stamp + CLOCKS[clock[0]][0] / 2
        for signal, rank, value in readings:
            if stamp is None:
                if clock is None:
                    self.counters.unstamped += 1
                continue
            if signal not in self.config.staleness:
                self.counters.unknown += 1
                continue
            if not math.isfinite(value):
                self.counters.invalid += 1
                continue
            assert taken is not None
            self._remember((signal, rank), taken, value)
        return self._due()

    def _remember(self, key: tuple[str, int], stamp: float, value: float) -> None:
        history = self._history.setdefault(key, [])
        position = len(history)
        while position and history[position - 1][0] > stamp:
            position -= 1
        history.insert(position, (stamp, value))
        if len(history) > HISTORY:
            del history[0]

    def _due(self) -> list[Tick]:
        if self._frontier is None:
            return []
        period = self.config.period
        last_due = math.floor((self._frontier - self.config.wait) / period + 1e-9)
        ticks = []
        if last_due - self._next_k > MAX_GAP_SAMPLES:
            skipped = last_due - MAX_GAP_SAMPLES - self._next_k
            self.counters.count("gap", skipped)
            self._next_k += skipped
        while self._next_k <= last_due:
            ticks.append(self._tick(self._next_k * period))
            self._next_k += 1
        return ticks

    def _tick(self, vehicle_t: float) -> Tick:
        t = self._offset + vehicle_t
        self._last_t = t
        values: dict[str, float] = {}
        stamps: dict[str, float] = {}
        for signal, limits in self.config.staleness.items():
            value, reason, stamp = self._value(signal, limits, vehicle_t)
            if reason:
                if signal in self.config.optional:
                    values[signal] = 0.0
                    continue
                self.counters.count(reason)
                return Tick(t, vehicle_t, None, reason)
            values[signal] = value
            stamps[signal] = stamp
        self.counters.samples += 1
        return Tick(t, vehicle_t, values, "", stamps)

    def _value(self, signal: str, limits: tuple[float, ...], t: float) -> tuple[float, str, float]:
        """The value of the first fresh source at ``t`` and its stamp, or a reason."""
        seen = False
        tolerance = 1e-9
        for rank, limit in enumerate(limits):
            newest = None
            for stamp, value in reversed(self._history.get((signal, rank), ())):
                if stamp <= t + tolerance:
                    newest = (stamp, value)
                    break
            if newest is None:
                continue
            seen = True
            if t - newest[0] <= limit + tolerance:
                if rank:
                    self.counters.fallbacks[signal] = self.counters.fallbacks.get(signal, 0) + 1
                return newest[1], "", newest[0]
        return math.nan, (f"{signal} stale" if seen else f"no {signal}"), math.nan
