"""Replays a recorded log through the live service's decode → sample → identifier path.

The raw MAVLink frames of ``mavlink/raw/in`` go through ``HilService.process_datagram``
exactly as they did live; the control inputs each decision used come from the log's
decision-inputs channel, applied at the same sample; the service configuration is
rebuilt from the log's metadata (``ServiceConfig.from_stored``) and the service wired by
``hil_service.builder`` as ``serve`` wires it. With ``check``, every recomputed estimate and
command is compared, as published bytes, with the recorded one, and the first difference
is reported. A decision-inputs record that cannot be read (not JSON, a field missing or of the
wrong type) is counted and skipped (``ReplayResult.skipped_inputs``), the first one named.
Timed replay sleeps to absolute deadlines derived from the log's timestamps, so it does not
drift over long logs.
"""

from __future__ import annotations

import json
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from hil_service.builder import wire
from hil_service.config import (
    ServiceConfig,
    sample_period_delay_problem,
    shown_json,
    stored_profile,
)
from hil_service.inputs import ControlInputs, Inbox
from hil_service.listeners import Listener
from hil_service.mcap.reader import LogMessage, LogReader
from hil_service.mcap.recorder import RAW_TOPIC
from hil_service.service import HilService
from protocols import keys, payload_json
from protocols.keys import CHANNELS
from protocols.payload_json import is_finite_number
from protocols.profiles import Profile, load_profile
from protocols.samples import TelemetrySample

RAW_IN = RAW_TOPIC.format(direction="in")
CHECKED_KINDS = (keys.UMODEL, keys.COMMAND_BALLAST)


class ReplayError(Exception):
    """The log cannot be replayed (no raw frames, no stored configuration for --check)."""


@dataclass(frozen=True)
class ReplayOptions:
    speed: float | None = None  # None: as fast as possible
    check: bool = False
    model: str | None = None  # override the stored model (disables bit-for-bit checking)
    profile: str | None = None  # a vehicle profile (name or file); default: the log's own
    #: Periodic profiles; default: an explicit profile's period, else the log's, else its profile's.
    sample_period: float | None = None
    progress: Callable[[int, int], None] | None = None  # (bytes read, file size)


@dataclass
class Mismatch:
    key: str
    index: int
    t: float | None
    recorded: str
    recomputed: str

    def describe(self) -> str:
        return (
            f"first difference on {self.key} at message #{self.index}"
            f"{'' if self.t is None else f' (t = {self.t:g} s)'}:\n"
            f"  recorded:   {self.recorded[:300]}\n  recomputed: {self.recomputed[:300]}"
        )


@dataclass
class ReplayResult:
    samples: int = 0
    frames: int = 0
    compared: int = 0
    mismatch: Mismatch | None = None
    recovered: str = ""
    complete: bool = True
    wall_s: float = 0.0
    lag_s: float = 0.0  # timed replay: worst lateness behind the schedule
    summary: dict[str, Any] = field(default_factory=dict)
    #: Decision-inputs records that could not be read, skipped; and why the first was.
    skipped_inputs: int = 0
    first_skipped: str = ""
    #: What the service's MAVLink decoder could not use (its ``ParseCounters``) and raw
    #: records with no bytes at all: a log of only these replays to 0 samples.
    bad_frames: int = 0
    unknown_frames: int = 0
    empty_frames: int = 0

    def unusable(self) -> str:
        """The frames that gave nothing, as the summary line says it ("" when none)."""
        counts = (
            (self.bad_frames, "bad frames"),
            (self.unknown_frames, "frames of unknown messages"),
            (self.empty_frames, "empty records"),
        )
        return ", ".join(f"{count} {what}" for count, what in counts if count)


class ReplayInbox(Inbox):
    """Control inputs as the live service applied them, each at the sample it was stamped with.

    Events arrive in file order while the log is read (see ``replay``), always before the
    sample they apply to is processed.
    """

    def __init__(self) -> None:
        super().__init__()
        self._events: dict[int, deque[dict[str, Any]]] = defaultdict(deque)
        self._current: dict[int, dict[str, Any]] = {}

    def add_event(self, system_id: int, event: dict[str, Any]) -> None:
        self._events[system_id].append(event)

    def inputs_for(self, sample: TelemetrySample) -> ControlInputs:
        events = self._events.get(sample.system_id)
        reset = False
        while events and events[0]["time_boot_ms"] <= sample.time_boot_ms:
            event = events.popleft()
            self._current[sample.system_id] = event
            reset = reset or (
                event["time_boot_ms"] == sample.time_boot_ms and event.get("reset", False)
            )
        current = self._current.get(sample.system_id)
        if current is None:
            return ControlInputs()
        return ControlInputs(dict(current["setpoints"]), current["enabled"], reset)


class Collector(Listener):
    """Keeps what the replayed service publishes on the checked keys, as the bytes the live
    service sent, to compare with the log's."""

    def __init__(self) -> None:
        self.published: dict[str, deque[bytes]] = defaultdict(deque)

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        if _kind(key) in CHECKED_KINDS:
            self.published[key].append(data)


def _kind(key: str) -> str:
    parsed = keys.parse(key)
    return "" if parsed is None else parsed.kind


def replay(
    path: str | Path | Sequence[str | Path],
    options: ReplayOptions,
    listeners: Sequence[Any] = (),
) -> ReplayResult:
    """One pass over the log: its raw frames through the service, compared if ``check``.

    ``path`` may be the files of one log rotated by ``serve`` (``--log-max-mb``,
    ``--log-max-s``), in order: they are replayed as one run through one service, each
    checked to continue the one before it (``LogReader.part``). With ``check`` the first
    must be the log's first part: the identifiers of a later part start in the ones before.

    In file order a sample's decision inputs (and its published estimates and command)
    follow the frame that completed the sample and precede the next sample's frames, as
    the live service logged them. So each raw frame is held until the next one is read:
    by then the inputs it needs are known, and the records to compare with are at hand.
    """
    paths = [Path(path)] if isinstance(path, str | Path) else [Path(p) for p in path]
    if not paths:
        raise ReplayError("no log to replay")
    return _Replay(paths, options, listeners).run()


class _Replay:
    def __init__(self, paths: list[Path], options: ReplayOptions, listeners: Sequence[Any]) -> None:
        self.path = paths[0]
        self.options = options
        self.readers = [LogReader(path) for path in paths]
        self.reader = self.readers[0]  # its stored configuration is the run's
        self.inbox = ReplayInbox()
        self.collector = Collector()
        #: The replayed service's listeners: the collector (with ``check``), then the
        #: caller's (``replay --publish``, ``--foxglove``).
        self.listeners = [*([self.collector] if options.check else []), *listeners]
        self.service: HilService | None = None
        self.result = ReplayResult()
        self.recorded_index: dict[str, int] = defaultdict(int)
        self.to_compare: list[LogMessage] = []
        self.started = time.monotonic()
        self.first_log_ns: int | None = None

    def run(self) -> ReplayResult:
        pending: LogMessage | None = None
        stopped = False
        for number, reader in enumerate(self.readers):
            checked = False
            for message in _messages(reader, self.options):
                if not checked:  # its metadata precede its first message
                    self._check_part(number, reader)
                    checked = True
                topic = message.topic
                if topic == RAW_IN:
                    if pending is not None and not self._feed(pending):
                        pending, stopped = None, True
                        break
                    pending = message
                    continue
                parsed = keys.parse(topic)
                if parsed is None:
                    continue
                if parsed.kind == keys.DECISION_INPUTS:
                    self._add_inputs(parsed.system_id, message)
                elif self.options.check and parsed.kind in CHECKED_KINDS:
                    self.to_compare.append(message)
            if stopped:
                break
        if pending is not None:
            self._feed(pending)
        if self.service is None:
            raise ReplayError(f"{self.path}: no {RAW_IN} frames to replay")
        return self._finish()

    def _check_part(self, number: int, reader: LogReader) -> None:
        """The ``number``-th file given continues the one before it; with ``check`` the first
        is a first part. A file that does not say which part it is is taken as given."""
        part = reader.part()
        if part is None:
            return
        index, previous = part
        if number == 0:
            if index > 1 and self.options.check:
                raise ReplayError(
                    f"{reader.path} is part {index} of a rotated log (it continues {previous}):"
                    " --check follows a run from its first part; give the parts in order, "
                    f"from the first, e.g. glider-hil replay --check ... {previous} "
                    f"{reader.path.name}"
                )
            return
        before = self.readers[number - 1].path.name
        if previous != before:
            follows = f"it continues {previous}" if previous else "it is a first part"
            raise ReplayError(f"{reader.path} does not continue {before} ({follows})")

    def _add_inputs(self, system_id: int, message: LogMessage) -> None:
        """A decision-inputs record to the inbox; one that cannot be read is counted and
        skipped, the first one named (channel, log time and what is wrong)."""
        try:
            event = decision_event(_decoded(message))
        except ValueError as error:
            result = self.result
            result.skipped_inputs += 1
            if not result.first_skipped:
                at = datetime.fromtimestamp(message.log_time_ns / 1e9, UTC).isoformat()
                result.first_skipped = f"{message.topic} at log time {at}: {error}"
            return
        self.inbox.add_event(system_id, event)

    def _feed(self, frame: LogMessage) -> bool:
        """Process one raw frame, then compare what was logged since; False on a mismatch."""
        service = self.service or self._start()
        options, result = self.options, self.result
        if options.speed is not None:
            if self.first_log_ns is None:
                self.first_log_ns = frame.log_time_ns
            offset_s = (frame.log_time_ns - self.first_log_ns) / 1e9 / options.speed
            result.lag_s = max(result.lag_s, _wait_until(self.started + offset_s))
        if not frame.data:
            result.empty_frames += 1
        service.process_datagram(frame.data)
        result.frames += 1
        for message in self.to_compare:
            mismatch = _compare(message, self.collector, self.recorded_index)
            result.compared += 1
            if mismatch is not None:
                result.mismatch = mismatch
                return False
        self.to_compare.clear()
        return True

    def _start(self) -> HilService:
        """The service as the log's metadata describes it (metadata precedes all messages)."""
        stored = self.reader.config()
        config = ServiceConfig.from_stored(stored, self.path)
        if config is None:
            if self.options.check:
                raise ReplayError(f"{self.path}: no stored configuration, cannot --check")
            config = ServiceConfig()
        if self.options.model is not None:
            model = self.options.model
            chosen = bool(config.pipeline.choose_input_lags) and model == "dynamic"
            pipeline = config.pipeline.replace(model=model, choose_input_lags=chosen)
            config = replace(config, pipeline=pipeline)
        profile = self._profile(stored) or config.profile
        period = self._sample_period(profile, stored)
        config = replace(config, profile=profile, sample_period=period)
        wired = wire(config, inbox=self.inbox, listeners=self.listeners, send_commands=False)
        self.service = wired.service
        return self.service

    def _profile(self, stored: dict[str, Any]) -> Profile | None:
        """``--profile``, else the profile the log stores (serve and import store theirs)."""
        if self.options.profile is not None:
            return load_profile(self.options.profile)
        return stored_profile(stored, self.path)

    def _sample_period(self, profile: Profile, stored: dict[str, Any]) -> float | None:
        """The period replayed with a periodic ``profile`` (None for a lockstep one), the most
        explicit first: ``--sample-period``; the period of a ``--profile`` given (the user
        chose it, not the log); the period the log recorded; the profile's."""
        given = self.options.sample_period
        if profile.sampling.mode != "periodic":
            if given is not None:
                raise ReplayError(
                    f"--sample-period needs a periodic profile; {profile.name} is not"
                )
            return None
        if given is not None:
            problem = sample_period_delay_problem(profile, given)
            if problem:
                raise ReplayError(problem)
            return given
        recorded = ((stored.get("service") or {}).get("profile") or {}).get("sample_period")
        if self.options.profile is not None or recorded is None:
            return profile.sampling.period
        return float(recorded)

    def _finish(self) -> ReplayResult:
        result, service = self.result, self.service
        assert service is not None
        reports = [reader.report for reader in self.readers]
        result.samples = service.source.samples
        result.complete = all(report.complete for report in reports)
        # Only a read that reached the end can tell a damaged file (--check stops early).
        result.recovered = "; ".join(
            report.describe() for report in reports if report.ended and not report.intact
        )
        intact = all(report.intact for report in reports)
        result.wall_s = time.monotonic() - self.started
        result.summary = service.summary()
        counters = service.codec.counters
        result.bad_frames, result.unknown_frames = counters.bad_frames, counters.unknown_frames
        if self.options.check and result.mismatch is None and intact:
            # A finished log holds every publication: anything left over was never recorded.
            for key, queue in self.collector.published.items():
                if queue:
                    index = self.recorded_index[key]
                    recomputed = queue[0].decode()
                    result.mismatch = Mismatch(
                        key, index, _t(queue[0]), "<not in the log>", recomputed
                    )
                    break
        return result


def _decoded(message: LogMessage) -> Any:
    try:
        return message.json()
    except ValueError as error:
        raise ValueError(f"not JSON ({error})") from None


def decision_event(payload: Any) -> dict[str, Any]:
    """A decision-inputs record as ``ReplayInbox`` applies it (its schema:
    protocols/schemas/decision_inputs.json; ``reset`` may be absent). ValueError names the
    field that is missing or of the wrong type."""
    if not isinstance(payload, dict):
        raise ValueError(f"expected an object, got {shown_json(payload)}")
    stamp = payload.get("time_boot_ms")
    if isinstance(stamp, bool) or not isinstance(stamp, int) or stamp < 0:
        raise ValueError(f"time_boot_ms: expected an integer ≥ 0, got {shown_json(stamp)}")
    setpoints = payload.get("setpoints")
    if not _readable_setpoints(setpoints):
        raise ValueError(
            f"setpoints: expected an object of {' and '.join(CHANNELS)}, each a number or "
            f"null, got {shown_json(setpoints)}"
        )
    enabled = payload.get("enabled")
    if not isinstance(enabled, bool):
        raise ValueError(f"enabled: expected true or false, got {shown_json(enabled)}")
    reset = payload.get("reset", False)
    if not isinstance(reset, bool):
        raise ValueError(f"reset: expected true or false, got {shown_json(reset)}")
    return payload


def _readable_setpoints(setpoints: Any) -> bool:
    """An object holding every channel's setpoint, each a number or null (a NaN is stored
    as null)."""
    return (
        isinstance(setpoints, dict)
        and all(channel in setpoints for channel in CHANNELS)
        and all(value is None or is_finite_number(value) for value in setpoints.values())
    )


def _messages(reader: LogReader, options: ReplayOptions) -> Iterator[LogMessage]:
    for message in reader.messages():
        if options.progress is not None and message.topic == RAW_IN:
            options.progress(reader.report.bytes_read, reader.report.file_size)
        yield message


def _wait_until(deadline: float) -> float:
    """Sleep to an absolute deadline; return how late we already were (s), 0 if on time."""
    now = time.monotonic()
    if now >= deadline:
        return now - deadline
    time.sleep(deadline - now)
    return 0.0


def _compare(
    message: LogMessage, collector: Collector, recorded_index: dict[str, int]
) -> Mismatch | None:
    key = message.topic
    index = recorded_index[key]
    recorded_index[key] += 1
    queue = collector.published.get(key)
    if not queue:
        return Mismatch(key, index, _t(message.data), message.data.decode(), "<nothing>")
    recomputed = queue.popleft()
    if recomputed != message.data and not _same_values(recomputed, message.data):
        return Mismatch(key, index, _t(message.data), message.data.decode(), recomputed.decode())
    return None


def _same_values(recomputed: bytes, recorded: bytes) -> bool:
    """Equal once both are in one canonical encoding: a log written by another JSON encoder
    (other spacing or float spelling) still checks bit for bit, since floats round-trip."""
    try:
        return payload_json.encode(payload_json.decode(recorded)) == recomputed
    except ValueError:
        return False


def _t(data: bytes) -> float | None:
    try:
        return float(json.loads(data)["t"])
    except (ValueError, KeyError, TypeError):
        return None
