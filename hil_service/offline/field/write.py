"""A field data set as the MCAP log a live glider's service would record (docs/mcap.md).

Each grid sample becomes the plant step of the ``glider`` profile (protocols/mapping.py):
ATTITUDE, SCALED_PRESSURE2, VFR_HUD and ACTUATOR_OUTPUT_STATUS, all stamped with one
``time_boot_ms``, framed as the vehicle (system ``system_id``, the autopilot component),
on ``mavlink/raw/in`` and decoded on ``mavlink/json/in/*``; the vehicle's HEARTBEAT at each
segment start and every ``HEARTBEAT_EVERY`` samples. The sample itself is on
``glider/{id}/telemetry`` (its schema ``glider-hil.telemetry``), so ``replay`` runs the
service's own path over it and ``report`` reads it. ``time_boot_ms`` counts from the first
grid sample (+1 s); the log time is the sample's real time. Between segments (a surface
interval) the clock jumps on: the service's step continuity sees a gap.

Inputs are in model units: ``full_scale``·(x − centre)/half_range (``InputScaling``); a
value beyond full scale is clipped and counted. The stored configuration holds ``source``,
``profile`` (the glider profile) and ``field``: the format, files, vehicle, conversions,
input scaling, the reader's counts, the grid and its segments (docs/mcap.md).
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.mcap.recorder import McapRecorder
from hil_service.offline.field.grid import GridResult
from hil_service.offline.field.table import FieldData
from hil_service.offline.log_output import move_into_place, refuse_directory
from protocols import keys
from protocols.mapping import AUTOPILOT_COMPONENT, TelemetryMapping
from protocols.mavlink_io import MavlinkCodec
from protocols.profiles import load_profile
from protocols.samples import TelemetrySample
from protocols.units import InputScale

FIELD_KEY = "field"
HEARTBEAT_EVERY = 10
FULL_SCALE = 2.0
MAX_BACKLOG = 200_000
BOOT_OFFSET_MS = 1000


@dataclass(frozen=True)
class WriteReport:
    output: str
    samples: int
    frames: int
    clipped: dict[str, int]

    def as_dict(self) -> dict[str, Any]:
        return {
            "output": self.output,
            "samples": self.samples,
            "frames": self.frames,
            "clipped": dict(self.clipped),
        }


def model_inputs(data: FieldData, grid: GridResult) -> tuple[np.ndarray, np.ndarray, dict]:
    """(u_depth, u_pitch) in model units, clipped to full scale, and the clip counts."""
    out = []
    clipped = {}
    for quantity, native in (("buoyancy", grid.buoyancy), ("pitch_input", grid.pitch_input)):
        u = data.scaling[quantity].to_model(native, FULL_SCALE)
        over = np.abs(u) > FULL_SCALE
        clipped[quantity] = int(np.count_nonzero(over))
        out.append(np.clip(u, -FULL_SCALE, FULL_SCALE))
    return out[0], out[1], clipped


def field_metadata(data: FieldData, grid: GridResult, clipped: dict[str, int]) -> dict[str, Any]:
    return {
        "format": data.format,
        "vehicle": data.vehicle,
        "files": list(data.files),
        "conversions": [c.as_dict() for c in data.conversions],
        "scaling": {k: v.as_dict() for k, v in data.scaling.items()},
        "full_scale": FULL_SCALE,
        "inputs": {"u_depth": "buoyancy", "u_pitch": "pitch_input"},
        "issues": data.issues.as_dict(),
        "grid": grid.as_dict(),
        "clipped": dict(clipped),
        "boot_offset_ms": BOOT_OFFSET_MS,
    }


def write_field_log(
    data: FieldData, grid: GridResult, output: str | Path, system_id: int = 1
) -> WriteReport:
    output = Path(output)
    refuse_directory(output)
    profile = load_profile("glider")
    u_depth, u_pitch, clipped = model_inputs(data, grid)
    metadata = {
        "source": json.dumps(
            {"kind": "field import", "format": data.format, "files": list(data.files)}
        ),
        "profile": json.dumps({"name": profile.name, "text": profile.text}),
        FIELD_KEY: json.dumps(field_metadata(data, grid, clipped)),
    }
    mapping = TelemetryMapping(inputs=InputScale(FULL_SCALE))
    codec = MavlinkCodec(system_id, AUTOPILOT_COMPONENT)
    heartbeat = mapping.heartbeat()
    starts = {s.start for s in grid.segments}
    t0 = float(grid.t[0]) if grid.size else 0.0
    key = keys.telemetry(system_id)
    frames = 0
    output.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=output.parent, prefix=".import-") as scratch:
        recorder = McapRecorder(scratch, metadata, max_bytes=1 << 62, max_seconds=1e12).start()
        try:
            for k in range(grid.size):
                t = float(grid.t[k])
                t_ns = round(t * 1e9)
                ms = round((t - t0) * 1000.0) + BOOT_OFFSET_MS
                sample = TelemetrySample(
                    system_id,
                    ms,
                    float(grid.depth[k]),
                    float(grid.pitch[k]),
                    float(u_depth[k]),
                    float(u_pitch[k]),
                )
                messages = mapping.encode_telemetry(sample)
                if k in starts or k % HEARTBEAT_EVERY == 0:
                    messages.insert(0, heartbeat)
                for message in messages:
                    recorder.raw("in", codec.pack(message), t_ns)
                    recorder.mavlink("in", message, t_ns)
                    frames += 1
                recorder.zenoh(key, sample.to_payload(), "out", t_ns)
                while recorder.backlog > MAX_BACKLOG:
                    time.sleep(0.01)  # let the writer thread catch up rather than drop
        finally:
            recorder.close(timeout=600)
        if recorder.status.error:
            raise OSError(f"writing {output}: {recorder.status.error}")
        (written,) = recorder.status.files
        move_into_place(written, output)
    return WriteReport(str(output), grid.size, frames, clipped)
