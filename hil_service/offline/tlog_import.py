"""A telemetry log (``.tlog``, as MAVProxy and QGroundControl write it) into our MCAP layout.

A tlog is a sequence of records, each an 8-byte big-endian timestamp (µs since the Unix
epoch) followed by one MAVLink frame (1 or 2, its length from its own header). The import
writes what the service's recorder writes (``hil_service.mcap.recorder``): the raw frames on
``mavlink/raw/in`` (the vehicle's) and ``mavlink/raw/out`` (everyone else's: ground
stations, companions), each decoded message as JSON with its schema on
``mavlink/json/{in,out}/TYPE``, and, in the stored configuration, where it came from and
the vehicle profile (``profile``: name and TOML text), so ``info``, ``report`` and
``replay`` work on it.

The vehicle is the system whose autopilot (a HEARTBEAT that is neither a ground station
nor an onboard controller, from a real autopilot) is heard first, unless given. A damaged
tlog (a cut-off record, bytes that are no MAVLink frame) is read up to the damage, and
the report says at which byte and why; frames that fail their checksum are counted and
skipped, and so are records whose timestamp no log can hold (beyond 2554: MCAP stores
uint64 ns). A file with no record to write, or a chosen vehicle
that sent no frame, is a ``TlogError``.
"""

from __future__ import annotations

import json
import struct
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from hil_service.mcap.recorder import McapRecorder
from hil_service.offline.field.table import MAX_LOG_TIME_NS
from hil_service.offline.log_output import move_into_place, refuse_directory
from protocols.mavlink_io import MavlinkCodec, MavMessage, dialect, frame_length
from protocols.profiles import Profile

TIMESTAMP = struct.Struct(">Q")
NOT_VEHICLES = frozenset(
    {
        dialect.MAV_TYPE_GCS,
        dialect.MAV_TYPE_ONBOARD_CONTROLLER,
        dialect.MAV_TYPE_GIMBAL,
        dialect.MAV_TYPE_ADSB,
        dialect.MAV_TYPE_CAMERA,
    }
)
COMPANION_COMPONENT = dialect.MAV_COMP_ID_ONBOARD_COMPUTER
MAX_BACKLOG = 200_000  # records the recorder may hold before the import waits for it


class TlogError(ValueError):
    """A tlog that cannot be imported: the message names the file and why."""


class TlogRecord(NamedTuple):
    t_us: int
    offset: int  # byte offset of the record (its timestamp) in the file
    frame: bytes


@dataclass
class TlogReport:
    path: str
    records: int = 0
    bytes_read: int = 0
    size: int = 0
    damage: str = ""  # empty when the whole file was read
    bad_frames: int = 0  # frames that failed their checksum or could not be decoded
    unknown_frames: int = 0
    bad_times: int = 0  # records whose timestamp no log can hold: skipped
    vehicle: int | None = None
    directions: dict[str, int] = field(default_factory=lambda: {"in": 0, "out": 0})

    @property
    def complete(self) -> bool:
        return not self.damage

    def describe(self) -> str:
        read = f"{self.records} records ({self.bytes_read} of {self.size} bytes)"
        if self.complete:
            return f"{self.path}: {read}, complete"
        return f"{self.path}: {read}; stopped: {self.damage}"

    def as_dict(self) -> dict[str, object]:
        return {
            "path": self.path,
            "records": self.records,
            "bytes_read": self.bytes_read,
            "size": self.size,
            "complete": self.complete,
            "damage": self.damage,
            "bad_frames": self.bad_frames,
            "unknown_frames": self.unknown_frames,
            "bad_times": self.bad_times,
            "vehicle_system_id": self.vehicle,
            "frames": dict(self.directions),
        }


def read_tlog(path: str | Path, report: TlogReport | None = None) -> Iterator[TlogRecord]:
    """The records of a tlog up to its end or its first damage (written to ``report``)."""
    data = Path(path).read_bytes()
    report = report if report is not None else TlogReport(str(path))
    report.size = len(data)
    position = 0
    while position < len(data):
        if len(data) - position < TIMESTAMP.size + 3:
            report.damage = f"byte {position}: a record cut off after {len(data) - position} bytes"
            return
        (t_us,) = TIMESTAMP.unpack_from(data, position)
        start = position + TIMESTAMP.size
        length = frame_length(data, start)
        if length is None:
            report.damage = (
                f"byte {start}: 0x{data[start]:02x} where a MAVLink frame should start "
                f"(record {report.records + 1})"
            )
            return
        if start + length > len(data):
            report.damage = (
                f"byte {position}: record {report.records + 1} cut off "
                f"({len(data) - start} of {length} frame bytes)"
            )
            return
        yield TlogRecord(t_us, position, data[start : start + length])
        position = start + length
        report.records += 1
        report.bytes_read = position


def find_vehicle(path: str | Path) -> int | None:
    """The system id of the first autopilot heard in a tlog (None when there is none)."""
    return next(_autopilots(path), None)


def autopilots_heard(path: str | Path) -> list[int]:
    """The system ids of every autopilot heard in a tlog, in the order first heard."""
    return list(dict.fromkeys(_autopilots(path)))


def _autopilots(path: str | Path) -> Iterator[int]:
    codec = MavlinkCodec(0, 0)
    for record in read_tlog(path):
        for message in codec.parse(record.frame, datagram=True):
            if _is_vehicle_heartbeat(message):
                yield int(message.get_srcSystem())


def _silent_vehicle(path: Path, vehicle: int) -> TlogError:
    """A chosen vehicle that sent no frame: the log would hold none of its own."""
    heard = ", ".join(map(str, autopilots_heard(path))) or "none"
    return TlogError(
        f"{path}: no frame from vehicle {vehicle} (the autopilots heard: {heard}; "
        "--vehicle takes one of them)"
    )


def _is_vehicle_heartbeat(message: MavMessage) -> bool:
    return (
        message.get_type() == "HEARTBEAT"
        and message.type not in NOT_VEHICLES
        and message.autopilot != dialect.MAV_AUTOPILOT_INVALID
    )


def import_tlog(
    path: str | Path,
    output: str | Path,
    profile: Profile,
    vehicle: int | None = None,
) -> TlogReport:
    """Write ``path`` (a tlog) as the MCAP log ``output``; the report says what was read.
    TlogError when ``vehicle`` sent no frame or no record could be written."""
    source = Path(path)
    output = Path(output)
    refuse_directory(output)
    report = TlogReport(str(source))
    report.vehicle = vehicle if vehicle is not None else find_vehicle(source)
    metadata = {
        "source": json.dumps({"kind": "tlog import", "tlog": str(source)}),
        "profile": json.dumps({"name": profile.name, "text": profile.text}),
    }
    output.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=output.parent, prefix=".import-") as scratch:
        recorder = McapRecorder(scratch, metadata, max_bytes=1 << 62, max_seconds=1e12).start()
        try:
            _write(recorder, source, report)
        finally:
            recorder.close(timeout=600)
        if recorder.status.error:
            raise OSError(f"writing {output}: {recorder.status.error}")
        if not sum(report.directions.values()):
            raise _nothing_written(report)
        if vehicle is not None and not report.directions["in"]:
            raise _silent_vehicle(source, vehicle)  # before the output is written
        (written,) = recorder.status.files
        move_into_place(written, output)
    return report


def _nothing_written(report: TlogReport) -> TlogError:
    if report.records and report.bad_times == report.records:
        return TlogError(
            f"{report.path}: no record has a time a log can hold (up to 2554-07-21; "
            f"{report.records} records): are the timestamps µs since 1970?"
        )
    stopped = f" ({report.damage})" if report.damage else ""
    return TlogError(f"{report.path}: no MAVLink record{stopped}")


def _write(recorder: McapRecorder, source: Path, report: TlogReport) -> None:
    codec = MavlinkCodec(0, 0)
    for record in read_tlog(source, report):
        t_ns = record.t_us * 1000
        if t_ns > MAX_LOG_TIME_NS:
            report.bad_times += 1
            continue
        before = (codec.counters.bad_frames, codec.counters.unknown_frames)
        messages = codec.parse(record.frame, datagram=True)
        report.bad_frames += codec.counters.bad_frames - before[0]
        report.unknown_frames += codec.counters.unknown_frames - before[1]
        direction = _direction(record.frame, report.vehicle)
        report.directions[direction] += 1
        recorder.raw(direction, record.frame, t_ns)
        for message in messages:
            recorder.mavlink(direction, message, t_ns)
        while recorder.backlog > MAX_BACKLOG:
            time.sleep(0.01)  # let the writer thread catch up rather than drop records


def _direction(frame: bytes, vehicle: int | None) -> str:
    """``in`` for a frame from the vehicle (not its companion computer), else ``out``."""
    if frame[0] == dialect.PROTOCOL_MARKER_V2:
        system, component = frame[5], frame[6]
    else:
        system, component = frame[3], frame[4]
    if vehicle is None:
        return "in" if system != 255 else "out"
    return "in" if system == vehicle and component != COMPANION_COMPONENT else "out"
