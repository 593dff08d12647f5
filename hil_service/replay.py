"""Replays a recorded log through the live service's decode → sample → identifier path.

The raw MAVLink frames of ``mavlink/raw/in`` go through ``HilService.process_datagram``
exactly as they did live; the control inputs each decision used come from the log's
decision-inputs channel, applied at the same sample; the identifier configuration is
rebuilt from the log's metadata. With ``check``, every recomputed estimate and command is
compared, as published bytes, with the recorded one, and the first difference is reported.
Timed replay sleeps to absolute deadlines derived from the log's timestamps, so it does not
drift over long logs.
"""

from __future__ import annotations

import json
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil_service.bus import Bus, ControlInputs, Inbox, NullBus
from hil_service.logreader import LogMessage, LogReader
from hil_service.service import HilService, ServiceConfig
from hil_service.vehicle import PipelineSettings
from protocols import payload_json
from protocols.mapping import TelemetryMapping
from protocols.samples import TelemetrySample
from protocols.units import InputScale, PressureDepth

RAW_IN = "mavlink/raw/in"
CHECKED_KINDS = ("umodel", "command")


class ReplayError(Exception):
    """The log cannot be replayed (no raw frames, no stored configuration for --check)."""


@dataclass(frozen=True)
class ReplayOptions:
    speed: float | None = None  # None: as fast as possible
    check: bool = False
    model: str | None = None  # override the stored model (disables bit-for-bit checking)
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


class ReplayInbox(Inbox):
    """Control inputs as the live service applied them, looked up by sample time."""

    def __init__(self, events: dict[int, list[dict[str, Any]]]):
        super().__init__()
        self._events = {sid: sorted(evs, key=lambda e: e["time_boot_ms"]) for sid, evs in
                        events.items()}  # fmt: skip
        self._cursor: dict[int, int] = defaultdict(int)
        self._current: dict[int, dict[str, Any]] = {}

    def inputs_for(self, sample: TelemetrySample) -> ControlInputs:
        events = self._events.get(sample.system_id, [])
        i = self._cursor[sample.system_id]
        reset = False
        while i < len(events) and events[i]["time_boot_ms"] <= sample.time_boot_ms:
            self._current[sample.system_id] = events[i]
            reset = reset or (events[i]["time_boot_ms"] == sample.time_boot_ms
                              and events[i].get("reset", False))  # fmt: skip
            i += 1
        self._cursor[sample.system_id] = i
        current = self._current.get(sample.system_id)
        if current is None:
            return ControlInputs()
        return ControlInputs(dict(current["setpoints"]), current["enabled"], reset)


class RecordingBus(NullBus):
    """Keeps what the replayed service publishes, as the bytes the live bus would send."""

    def __init__(self, inner: Bus | None = None, capture: bool = True):
        self.inner = inner
        self.capture = capture
        self.published: dict[str, deque[bytes]] = defaultdict(deque)

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        if self.capture and _kind(key) in CHECKED_KINDS:
            self.published[key].append(payload_json.encode(payload))
        if self.inner is not None:
            self.inner.publish(key, payload, reliable)

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        if self.inner is not None:
            self.inner.declare_vehicle(system_id, state)

    def close(self) -> None:
        if self.inner is not None:
            self.inner.close()


def _kind(key: str) -> str:
    parts = key.split("/")
    return parts[2] if len(parts) > 2 and parts[0] == "glider" else ""


def stored_mapping(stored: dict[str, Any]) -> TelemetryMapping:
    """The unit conversions the live service used (defaults when the log has none)."""
    mapping = stored.get("mapping")
    if not mapping:
        return TelemetryMapping()
    return TelemetryMapping(
        pressure=PressureDepth(mapping["water_density"], mapping["surface_pressure"]),
        inputs=InputScale(mapping["full_scale"]),
    )


def stored_config(path: Path) -> tuple[ServiceConfig, dict[int, list[dict[str, Any]]], bool]:
    """First pass: the service configuration and the decision-inputs events of a log."""
    reader = LogReader(path)
    events: dict[int, list[dict[str, Any]]] = defaultdict(list)
    raw_frames = 0
    for message in reader.messages():
        if message.topic.startswith("glider-hil/") and message.topic.endswith("/decision-inputs"):
            events[int(message.topic.split("/")[1])].append(message.json())
        elif message.topic == RAW_IN:
            raw_frames += 1
    if raw_frames == 0:
        raise ReplayError(f"{path}: no {RAW_IN} frames to replay")
    config = reader.config().get("service")
    has_config = config is not None
    if config is None:
        return ServiceConfig(), dict(events), False
    pipeline = PipelineSettings.from_json(config["pipeline"])
    service = ServiceConfig(
        system_ids=tuple(config.get("system_ids", ())),
        control_default=config.get("control_default", False),
        stale_timeout=config.get("stale_timeout", 3.0),
        pipeline=pipeline,
    )
    return service, dict(events), has_config


def replay(path: str | Path, options: ReplayOptions, bus: Bus | None = None) -> ReplayResult:
    path = Path(path)
    config, events, has_config = stored_config(path)
    if options.check and not has_config:
        raise ReplayError(f"{path}: no stored configuration, cannot --check")
    if options.model is not None:
        config = ServiceConfig(
            system_ids=config.system_ids,
            control_default=config.control_default,
            stale_timeout=config.stale_timeout,
            pipeline=config.pipeline.replace(model=options.model),
        )
    recording = RecordingBus(bus, capture=options.check)
    mapping = stored_mapping(LogReader(path).metadata_only())
    service = HilService(
        config, recording, ReplayInbox(events), mapping=mapping, send_commands=False
    )
    reader = LogReader(path)
    result = ReplayResult()
    recorded_index: dict[str, int] = defaultdict(int)
    started = time.monotonic()
    first_log_ns: int | None = None
    for message in _messages(reader, options):
        if message.topic == RAW_IN:
            if options.speed is not None:
                first_log_ns = first_log_ns or message.log_time_ns
                result.lag_s = max(
                    result.lag_s,
                    _wait_until(
                        started + (message.log_time_ns - first_log_ns) / 1e9 / options.speed
                    ),
                )
            service.process_datagram(message.data)
            result.frames += 1
        elif options.check and _kind(message.topic) in CHECKED_KINDS:
            mismatch = _compare(message, recording, recorded_index)
            result.compared += 1
            if mismatch is not None:
                result.mismatch = mismatch
                break
    result.samples = service.assembler.counters.samples
    result.complete = reader.report.complete
    if reader.report.ended and not reader.report.complete:
        # Only a read that reached the end can tell a damaged file (--check stops early).
        result.recovered = reader.report.describe()
    result.wall_s = time.monotonic() - started
    result.summary = service.summary()
    if options.check and result.mismatch is None and reader.report.complete:
        # A finished log holds every publication: anything left over was never recorded.
        for key, queue in recording.published.items():
            if queue:
                result.mismatch = Mismatch(
                    key, recorded_index[key], _t(queue[0]), "<not in the log>", queue[0].decode()
                )
                break
    return result


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
    message: LogMessage, recording: RecordingBus, recorded_index: dict[str, int]
) -> Mismatch | None:
    key = message.topic
    index = recorded_index[key]
    recorded_index[key] += 1
    queue = recording.published.get(key)
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
