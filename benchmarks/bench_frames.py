"""The cost of framing one plant step's telemetry (the glider's four messages) and of
decoding it, pymavlink beside our codec, measured in one run (printed, not asserted).

    .venv/bin/python benchmarks/bench_frames.py [--steps 5000]

``pack``: pymavlink's ``MAVLink_message.pack`` against ``MavlinkCodec.pack`` (the
``FrameEncoder``); ``parse``: pymavlink's ``parse_buffer`` against ``MavlinkCodec.parse`` of
the same datagram (the ``FrameDecoder``). Prints one JSON object, µs per step (best of 7
rounds, the four taking turns in each).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from protocols import compiled  # noqa: E402
from protocols.mapping import TelemetryMapping  # noqa: E402
from protocols.mavlink_io import MavlinkCodec, dialect  # noqa: E402
from protocols.samples import TelemetrySample  # noqa: E402


def _best_us(
    actions: dict[str, Callable[[], object]], steps: int, rounds: int = 7
) -> dict[str, float]:
    """µs per call of each action, the best of ``rounds``; the actions take turns within
    each round, so a burst of load elsewhere hits them alike."""
    best = dict.fromkeys(actions, float("inf"))
    for _ in range(rounds):
        for name, action in actions.items():
            started = time.perf_counter()
            for _ in range(steps):
                action()
            best[name] = min(best[name], time.perf_counter() - started)
    return {name: round(1e6 * seconds / steps, 2) for name, seconds in best.items()}


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
    actions: dict[str, Callable[[], object]] = {
        "pack_pymavlink_us": lambda: [m.pack(packer) for m in reference],
        "pack_codec_us": lambda: [codec.pack(m) for m in messages],
        "parse_pymavlink_us": lambda: parser_mav.parse_buffer(datagram),
        "parse_codec_us": lambda: peer.parse(datagram, datagram=True),
    }
    print(json.dumps({"modules": compiled.summary(), **_best_us(actions, args.steps)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
