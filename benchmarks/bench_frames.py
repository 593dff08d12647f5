"""The cost of framing one plant step's telemetry (the glider's four messages) and of
decoding it, pymavlink beside our codec, measured in one run (printed, not asserted).

    .venv/bin/python benchmarks/bench_frames.py [--steps 5000]

``pack``: pymavlink's ``MAVLink_message.pack`` against ``MavlinkCodec.pack`` (the
``FrameEncoder``); ``parse``: pymavlink's ``parse_buffer`` against ``MavlinkCodec.parse`` of
the same datagram (the ``FrameDecoder``). Prints one JSON object, µs per step (best of 5).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from protocols import compiled  # noqa: E402
from protocols.mapping import TelemetryMapping  # noqa: E402
from protocols.mavlink_io import MavlinkCodec, dialect  # noqa: E402
from protocols.samples import TelemetrySample  # noqa: E402


def _best_us(action, steps: int) -> float:
    best = float("inf")
    for _ in range(5):
        started = time.perf_counter()
        for _ in range(steps):
            action()
        best = min(best, time.perf_counter() - started)
    return 1e6 * best / steps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=5000)
    args = parser.parse_args()
    sample = TelemetrySample(1, 120_000, 12.5, 0.05, 0.4, -0.2, 0.01, 0.1)
    messages = TelemetryMapping().encode_telemetry(sample)
    reference = [copy.deepcopy(m) for m in messages]
    packer = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
    codec = MavlinkCodec(1, 1)
    datagram = b"".join(codec.pack(m) for m in messages)
    parser_mav = dialect.MAVLink(None)
    parser_mav.robust_parsing = True
    peer = MavlinkCodec(255, 190)
    result = {
        "modules": compiled.summary(),
        "pack_pymavlink_us": _best_us(lambda: [m.pack(packer) for m in reference], args.steps),
        "pack_codec_us": _best_us(lambda: [codec.pack(m) for m in messages], args.steps),
        "parse_pymavlink_us": _best_us(lambda: parser_mav.parse_buffer(datagram), args.steps),
        "parse_codec_us": _best_us(lambda: peer.parse(datagram, datagram=True), args.steps),
    }
    print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in result.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
