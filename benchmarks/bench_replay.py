"""Replay speed: `replay --fast` with identification on both channels, beside the MCAP
reader alone yielding the same log's messages (target: ≥ 10,000 samples/s).

Run: .venv/bin/python benchmarks/bench_replay.py [--samples 100000]
The log is written by the service's own recorder from the emulator's plant (raw frames and
the stored configuration), so the replay path is exactly the one `glider-hil replay` runs.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.config import ServiceConfig  # noqa: E402
from hil_service.experiment.speed import rates  # noqa: E402
from hil_service.mcap.reader import LogReader  # noqa: E402
from hil_service.mcap.recorder import McapRecorder  # noqa: E402
from hil_service.offline.replay import ReplayOptions, replay  # noqa: E402
from hil_service.process_tuning import tune_for_service  # noqa: E402
from plant_emulator.excitation import build_channel_excitations  # noqa: E402
from plant_emulator.plant import GliderPlant, PlantConfig  # noqa: E402
from protocols.mapping import TelemetryMapping  # noqa: E402
from protocols.mavlink_io import MavlinkCodec  # noqa: E402


def write_log(log_dir: str, samples: int) -> Path:
    recorder = McapRecorder(log_dir, ServiceConfig().to_metadata(), max_bytes=1 << 40).start()
    plant = GliderPlant(PlantConfig(scenario="disturbed", seed=2))
    excitation = build_channel_excitations("steps", 2)
    codec, mapping = MavlinkCodec(1, 1), TelemetryMapping()
    t_ns = 0
    for k in range(samples):
        sample = plant.step(excitation["depth"].value(k), excitation["pitch"].value(k))
        for message in mapping.encode_telemetry(sample):
            recorder.raw("in", codec.pack(message), t_ns)
        t_ns += 20_000_000  # 50 samples/s
        if k % 5000 == 4999:
            while recorder.backlog > 20_000:
                time.sleep(0.01)
    recorder.close(timeout=600)
    return Path(recorder.status.files[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument(
        "--repeats", type=int, default=5, help="runs of each measurement (best and median shown)"
    )
    args = parser.parse_args()
    reader_s, replay_s = [], []
    with tempfile.TemporaryDirectory() as log_dir:
        path = write_log(log_dir, args.samples)
        tune_for_service()  # as `glider-hil replay` does
        for _ in range(args.repeats):
            started = time.perf_counter()
            messages = sum(1 for _ in LogReader(path).messages())
            reader_s.append(time.perf_counter() - started)
            started = time.perf_counter()
            result = replay(path, ReplayOptions())
            replay_s.append(time.perf_counter() - started)
    print(json.dumps({
        "samples": result.samples,
        "log_messages": messages,
        "repeats": args.repeats,
        "mcap_reader_samples_per_s": rates(args.samples, reader_s),
        "replay_fast_samples_per_s": rates(result.samples, replay_s),
        "replay_fast_ratio_to_reader_best": min(reader_s) / min(replay_s),
    }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
