"""Samples formed per expected sample with MAVProxy, at its default stream rate, between
`glider-hil serve --profile ardusub --sample-period 0.1` and `emulate --profile ardusub`,
all on loopback: MAVProxy as a ground station lowers every stream to 4 Hz with
REQUEST_DATA_STREAM at start and every 15 s, and the companion asks for its rates again.

Run: .venv/bin/python benchmarks/ardusub_mavproxy.py [--speed 1] [--seconds 47]
     [--streamrate N]
Prints JSON: samples formed and expected (from the first to the last telemetry time, once
the companion's stream requests were all accepted), and the companion's re-requests.
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

from tests.conftest import ProcessGroup, free_tcp_port, free_udp_port  # noqa: E402
from tests.test_mavproxy_router import _mavproxy, _stop_mavproxy  # noqa: E402
from tests.zenoh_peer import ZenohProbe  # noqa: E402

PERIOD = 0.1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speed", type=float, default=1.0, help="emulator speed (default 1)")
    parser.add_argument("--seconds", type=float, default=47.0, help="wall s measured")
    parser.add_argument(
        "--streamrate", type=int, default=None, help="MAVProxy's --streamrate (default its own)"
    )
    args = parser.parse_args()
    scratch = Path(tempfile.mkdtemp(prefix="ardusub-mavproxy-"))
    group = ProcessGroup()
    master, udp, zport = free_udp_port(), free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    group.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
        "--profile", "ardusub", "--sample-period", str(PERIOD), "--sysid", "1",
    )  # fmt: skip
    extra = () if args.streamrate is None else (f"--streamrate={args.streamrate}",)
    router, console = _mavproxy(scratch, master, udp, scratch / "router.tlog", *extra)
    probe = ZenohProbe(endpoint)
    try:
        group.start(
            "emulate", "--profile", "ardusub", "--connect", f"udpout:127.0.0.1:{master}",
            "--speed", str(args.speed), "--period", str(PERIOD), "--excitation", "prbs",
        )  # fmt: skip

        def requests() -> dict:
            health = probe.latest("glider/1/health") or {}
            return (health.get("companion") or {}).get("stream_requests") or {}

        if not probe.wait_for(lambda: set(requests().values()) == {"accepted"}, 90):
            print(json.dumps({"error": "stream requests not accepted", "states": requests()}))
            return 1
        steady = probe.count("glider/1/telemetry")
        time.sleep(args.seconds)  # a measurement of so many wall seconds, not a readiness wait
        telemetry = probe.payloads("glider/1/telemetry")[steady:]
        companion = probe.latest("glider/1/health")["companion"]
    finally:
        probe.close()
        _stop_mavproxy(router, console)
        group.stop_all()
    times = [s["t"] for s in telemetry]
    expected = round((times[-1] - times[0]) / PERIOD) + 1
    print(
        json.dumps(
            {
                "speed": args.speed,
                "vehicle_s": round(times[-1] - times[0], 1),
                "samples": len(telemetry),
                "expected": expected,
                "formed_per_expected": round(len(telemetry) / expected, 4),
                "rerequests": companion["rerequests"],
                "slow_streams": companion["slow_streams"],
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
