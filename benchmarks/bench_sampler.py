"""Sample assembly throughput: the lockstep assembler (glider profile, one timestamp per
plant step) beside the asynchronous sampler (ardusub profile, four streams at the sample
rate, each stamped when sent with jitter), in the same run, on the same plant.

Run: .venv/bin/python benchmarks/bench_sampler.py [--samples 20000] [--repeats 5]
Both are fed decoded pymavlink messages (decoding is not timed). The lockstep assembler is
compiled by mypyc when built; the sampler and ProfileAssembler run as Python (they are not
in protocols/compiled.py's HOT_PATH).
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.sources.lockstep_assembler import SampleAssembler  # noqa: E402
from hil_service.sources.periodic_assembler import ProfileAssembler  # noqa: E402
from plant_emulator.excitation import build_channel_excitations  # noqa: E402
from plant_emulator.plant import GliderPlant, PlantConfig  # noqa: E402
from protocols.compiled import summary  # noqa: E402
from protocols.mapping import TelemetryMapping  # noqa: E402
from protocols.mavlink_io import MavlinkCodec, dialect  # noqa: E402
from protocols.profiles import load_profile  # noqa: E402

PERIOD = 0.1


def plant_samples(count: int) -> list:
    plant = GliderPlant(PlantConfig(scenario="disturbed", period=PERIOD, seed=2))
    excitation = build_channel_excitations("prbs", 2)
    return [
        plant.step(excitation["depth"].value(k), excitation["pitch"].value(k)) for k in range(count)
    ]


def decoded(codec: MavlinkCodec, messages: list) -> list:
    reader = MavlinkCodec(255, 0)
    return [m for message in messages for m in reader.parse(codec.pack(message), datagram=True)]


def lockstep_messages(samples: list) -> list:
    mapping = TelemetryMapping()
    return decoded(MavlinkCodec(1, 1), [m for s in samples for m in mapping.encode_telemetry(s)])


def ardusub_messages(samples: list, seed: int = 0) -> list:
    """Each stream at the sample rate, sent at its own jittered times (ZOH of the plant)."""
    profile = load_profile("ardusub")
    rng = random.Random(seed)
    ballast = profile.ballast
    events = []
    end = len(samples) * PERIOD
    for name in ("ATTITUDE", "SCALED_PRESSURE2", "VFR_HUD", "SERVO_OUTPUT_RAW"):
        t = rng.uniform(0, PERIOD)
        while t < end:
            events.append((t, name))
            t += PERIOD * (1 + rng.uniform(-0.1, 0.1))
    events.sort()
    out = []
    for t, name in events:
        s = samples[min(int(t / PERIOD), len(samples) - 1)]
        ms = int(t * 1000)
        if name == "ATTITUDE":
            out.append(dialect.MAVLink_attitude_message(ms, 0, s.pitch, 0, 0, s.pitch_rate, 0))
        elif name == "SCALED_PRESSURE2":
            hpa = profile.pressure.pressure_hpa(s.depth)
            out.append(dialect.MAVLink_scaled_pressure2_message(ms, hpa, 0, 1500, 0))
        elif name == "VFR_HUD":
            out.append(dialect.MAVLink_vfr_hud_message(0, 0, 0, 0, -s.depth, s.climb))
        else:
            servos = [1500] * 16
            servos[8] = ballast.pwm.from_wire(s.u_depth / ballast.full_scale)
            servos[9] = ballast.pwm.from_wire(s.u_pitch / ballast.full_scale)
            out.append(dialect.MAVLink_servo_output_raw_message(int(t * 1e6), 0, *servos))
    return decoded(MavlinkCodec(1, 1), out)


def time_lockstep(messages: list) -> tuple[int, float]:
    assembler = SampleAssembler()
    start = time.perf_counter()
    formed = sum(assembler.add(m) is not None for m in messages)
    return formed, time.perf_counter() - start


def time_periodic(messages: list) -> tuple[int, float, ProfileAssembler]:
    periodic = ProfileAssembler(load_profile("ardusub"), PERIOD)
    start = time.perf_counter()
    formed = sum(len(periodic.add_all(m)) for m in messages)
    return formed, time.perf_counter() - start, periodic


def rates(formed: int, seconds: list[float]) -> dict:
    per_s = sorted(formed / s for s in seconds)
    best, median = per_s[-1], statistics.median(per_s)
    return {
        "samples_per_s_best": round(best),
        "samples_per_s_median": round(median),
        "us_per_sample_best": round(1e6 / best, 2),
        "us_per_sample_median": round(1e6 / median, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=20_000)
    parser.add_argument(
        "--repeats", type=int, default=5, help="rounds, each timing both (interleaved)"
    )
    args = parser.parse_args()
    if args.samples < 1 or args.repeats < 1:
        parser.error("--samples and --repeats must be at least 1")
    samples = plant_samples(args.samples)
    lockstep = lockstep_messages(samples)
    ardusub = ardusub_messages(samples)

    # Interleaved rounds: this machine's speed drifts within minutes, so each round times
    # both paths back to back and the per-round ratio is the steadier figure.
    lockstep_s, periodic_s, ratios = [], [], []
    formed_lockstep = formed_periodic = 0
    periodic = None
    for _ in range(args.repeats):
        formed_lockstep, a = time_lockstep(lockstep)
        formed_periodic, b, periodic = time_periodic(ardusub)
        lockstep_s.append(a)
        periodic_s.append(b)
        ratios.append((b / max(formed_periodic, 1)) / (a / max(formed_lockstep, 1)))
    assert periodic is not None

    report = {
        "plant_steps": args.samples,
        "repeats": args.repeats,
        "hot_path": summary(),
        "lockstep": {
            "messages": len(lockstep),
            "samples": formed_lockstep,
            **rates(formed_lockstep, lockstep_s),
        },
        "periodic": {
            "messages": len(ardusub),
            "samples": formed_periodic,
            "formed_per_expected": round(formed_periodic / args.samples, 4),
            **rates(formed_periodic, periodic_s),
            "counters": periodic.counters.as_dict(),
        },
        "periodic_over_lockstep_per_sample_median": round(statistics.median(ratios), 2),
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
