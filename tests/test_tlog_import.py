"""`glider-hil import`: tlogs into MCAP logs; damaged tlogs are read up to the damage."""

from __future__ import annotations

import json
import struct

import pytest

from hil_service.cli import main
from hil_service.mcap.reader import LogReader
from hil_service.offline.tlog_import import TlogReport, find_vehicle, import_tlog, read_tlog
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import load_profile

T0 = 1_700_000_000_000_000  # µs since the epoch


def tlog_bytes(count: int = 20) -> tuple[bytes, list[int]]:
    """A vehicle (sysid 1) and a ground station (255) talking; the records' offsets."""
    vehicle, gcs = MavlinkCodec(1, 1), MavlinkCodec(255, 190)
    companion = MavlinkCodec(1, 191)
    data, offsets = b"", []
    for i in range(count):
        if i % 5 == 0:
            frame = gcs.pack(dialect.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3))
        elif i % 5 == 1:
            frame = vehicle.pack(dialect.MAVLink_heartbeat_message(12, 3, 0, 0, 4, 3))
        elif i % 5 == 2:
            frame = companion.pack(dialect.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
        else:
            frame = vehicle.pack(dialect.MAVLink_attitude_message(i * 100, 0, 0.1, 0, 0, 0, 0))
        offsets.append(len(data))
        data += struct.pack(">Q", T0 + i * 100_000) + frame
    return data, offsets


def test_a_whole_tlog_imports_with_directions_and_profile(tmp_path):
    data, _ = tlog_bytes()
    tlog = tmp_path / "dive.tlog"
    tlog.write_bytes(data)
    assert find_vehicle(tlog) == 1
    report = import_tlog(tlog, tmp_path / "dive.mcap", load_profile("ardusub"))
    assert report.complete and report.records == 20 and report.bytes_read == len(data)
    # The vehicle's autopilot is `in`; the ground station and the companion are `out`.
    assert report.directions == {"in": 12, "out": 8}
    reader = LogReader(tmp_path / "dive.mcap")
    messages = list(reader.messages())
    raw_in = [m for m in messages if m.topic == "mavlink/raw/in"]
    assert len(raw_in) == 12
    assert raw_in[0].log_time_ns == (T0 + 100_000) * 1000  # the tlog's own timestamps
    attitude = [m.json() for m in messages if m.topic == "mavlink/json/in/ATTITUDE"]
    assert attitude[0]["pitch"] == pytest.approx(0.1)
    assert reader.config()["profile"]["name"] == "ardusub"


@pytest.mark.parametrize(
    ("damage", "stops_at", "why"),
    [
        ("cut", 17, "cut off"),
        ("garbage", 9, "where a MAVLink frame should start"),
        ("short", 19, "a record cut off after"),
    ],
)
def test_a_damaged_tlog_is_read_up_to_the_damage(tmp_path, damage, stops_at, why):
    data, offsets = tlog_bytes()
    if damage == "cut":  # the file ends inside record 18's frame
        data = data[: offsets[17] + 8 + 5]
    elif damage == "garbage":  # record 10's frame start is overwritten
        data = data[: offsets[9] + 8] + b"\x42" + data[offsets[9] + 9 :]
    else:  # a few bytes of a 21st record
        data = data + b"\x00\x01\x02"
        stops_at = 20
    tlog = tmp_path / "damaged.tlog"
    tlog.write_bytes(data)
    report = TlogReport(str(tlog))
    records = list(read_tlog(tlog, report))
    assert len(records) == stops_at == report.records
    assert not report.complete and why in report.damage
    where = offsets[stops_at] if stops_at < len(offsets) else len(data) - 3
    if damage == "garbage":
        where += 8  # the frame's first byte, after the timestamp
    assert report.damage.startswith(f"byte {where}:")
    # The CLI writes what was read, says where it stopped, and exits 1.
    out = tmp_path / "damaged.mcap"
    code = main(["import", str(tlog), "-o", str(out), "--json"])
    assert code == 1
    assert sum(1 for m in LogReader(out).messages() if m.topic.startswith("mavlink/raw/")) == (
        stops_at
    )


def test_a_frame_failing_its_checksum_is_counted_and_skipped(tmp_path, capsys):
    data, offsets = tlog_bytes()
    corrupt = bytearray(data)
    corrupt[offsets[4] + 8 + 12] ^= 0xFF  # a payload byte of an ATTITUDE: CRC fails
    tlog = tmp_path / "crc.tlog"
    tlog.write_bytes(bytes(corrupt))
    code = main(["import", str(tlog), "-o", str(tmp_path / "crc.mcap"), "--json"])
    report = json.loads(capsys.readouterr().out)["import"]
    assert code == 0 and report["complete"] and report["bad_frames"] == 1
    assert report["records"] == 20
    assert main(["import", str(tlog), "-o", str(tmp_path / "crc.mcap")]) == 2  # exists
    assert main(["import", str(tmp_path / "absent.tlog"), "-o", str(tmp_path / "x.mcap")]) == 2


class _Capture:
    """A link that keeps what the emulated vehicle sends (no socket: a recorded dive)."""

    datagram = True

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def send(self, frame: bytes) -> None:
        self.frames.append(frame)


def ardusub_dive_tlog(path, steps: int) -> int:
    """A tlog of the ArduSub-style emulator on PRBS, every stream at 10 Hz, as a ground
    station records it (heartbeats included); the number of plant steps (0.1 s each)."""
    from plant_emulator.autopilot import AutopilotConfig
    from plant_emulator.excitation import build_channel_excitations
    from plant_emulator.plant import GliderPlant, PlantConfig
    from plant_emulator.streams import DEFAULT_RATES_HZ, ArduSubAutopilot, StreamConfig

    profile = load_profile("ardusub")
    link = _Capture()
    vehicle = ArduSubAutopilot(
        GliderPlant(PlantConfig(period=0.1, seed=5)),
        link,
        build_channel_excitations("prbs", seed=5),
        profile,
        AutopilotConfig(system_id=1),
        StreamConfig(rates_hz=dict.fromkeys(DEFAULT_RATES_HZ, 10.0), seed=5),
    )
    data = b""
    for k in range(steps):
        if k % 10 == 0:
            vehicle.send_heartbeat()
        vehicle.step()
        vehicle.send_streams_due(vehicle.sim_time())
        for frame in link.frames:
            data += struct.pack(">Q", T0 + k * 100_000) + frame
        link.frames.clear()
    path.write_bytes(data)
    return steps


def test_report_on_an_imported_tlog_identifies_from_its_telemetry(tmp_path, capsys):
    tlog, log, out = tmp_path / "dive.tlog", tmp_path / "dive.mcap", tmp_path / "report"
    steps = ardusub_dive_tlog(tlog, 1500)
    assert main(["import", str(tlog), "-o", str(log), "--profile", "ardusub"]) == 0
    # The imported log holds the vehicle's frames only: no estimate of the service's.
    assert not any(m.topic.startswith("glider/") for m in LogReader(log).messages())
    capsys.readouterr()
    assert main(["report", str(log), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "identified offline" in printed
    text = (out / "report.md").read_text()
    assert "- identified offline: the log holds no estimate records" in text
    rows = {
        cells[1]: cells
        for line in text.splitlines()
        if line.startswith("| 1 |")
        for cells in [[c.strip() for c in line.strip("|").split("|")]]
    }
    assert set(rows) == {"depth", "pitch"}, text
    for channel, cells in rows.items():
        samples, skill = int(cells[3]), float(cells[5])
        # Scored samples: those the identifier learnt from. A reading the sampler serves
        # twice (this dive's streams run at the sample rate) refills the history instead
        # of training the model (docs/control.md): 994 of 1,500 here, not every step.
        assert samples >= 0.6 * steps, (channel, samples)
        assert skill > 0, (channel, skill)  # better than persistence, after the burn-in
    assert (out / "glider1_depth_identification.png").exists()
