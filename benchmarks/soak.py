"""Soak run: emulator → faulty UDP relay → service for many samples, faults injected on a
schedule, control enabled throughout. Prints samples processed and lost, commands sent and
acknowledged, link fault counts, and the service's memory at the start, end and peak.

Run: .venv/bin/python benchmarks/soak.py [--samples 1000000] [--rate 600]
     [--drop 0.01] [--duplicate 0.005] [--reorder 0.005] [--outage-every 60] [--outage 3]

Everything runs on loopback with free ports; the service logs MCAP to a temporary directory
unless --log-dir is given. --rate is the emulator's steps per second (its --speed); keep it
below the service's end-to-end rate (benchmarks/bench_service.py) or UDP buffers overflow and
the loss figures measure the machine rather than the faults.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.cli.processes import free_port, last_json, start_verb, stop_process  # noqa: E402
from hil_service.listeners.zenoh_config import ZenohOptions, open_session  # noqa: E402
from protocols import keys  # noqa: E402
from tests.udp_relay import FaultyRelay  # noqa: E402


def memory_kib(pid: int) -> dict[str, int]:
    """VmRSS (now) and VmHWM (peak) of a process, KiB (Linux /proc)."""
    values = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(("VmRSS:", "VmHWM:")):
                name, value = line.split(":")
                values[name] = int(value.split()[0])
    except OSError:
        pass
    return values


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--rate", type=float, default=600.0, help="emulator steps per second")
    ap.add_argument("--drop", type=float, default=0.01)
    ap.add_argument("--duplicate", type=float, default=0.005)
    ap.add_argument("--reorder", type=float, default=0.005)
    ap.add_argument("--outage-every", type=float, default=60.0, help="wall s between outages")
    ap.add_argument("--outage", type=float, default=3.0, help="wall s the link is cut")
    ap.add_argument("--log-dir", default=None)
    args = ap.parse_args()

    tmp = tempfile.TemporaryDirectory(prefix="glider-hil-soak-")
    log_dir = args.log_dir or tmp.name
    udp, zport = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = start_verb(
        "serve", "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
        "--log-dir", log_dir, "--stale-timeout", "1.0", "--burn-in", "500",
    )  # fmt: skip
    relay = FaultyRelay(("127.0.0.1", udp), args.drop, args.duplicate, args.reorder, seed=1).start()
    time.sleep(1.0)
    session = open_session(ZenohOptions(connect=(endpoint,)))
    emulator = start_verb(
        "emulate", "--connect", f"udpout:127.0.0.1:{relay.port}", "--speed", str(args.rate),
        "--duration", str(args.samples), "--scenario", "disturbed", "--seed", "1",
        "--command-timeout", "50",
    )  # fmt: skip
    started = time.monotonic()
    memory_start: dict[str, int] = {}
    outages = 0
    next_outage = started + args.outage_every
    controlled = False
    try:
        while emulator.poll() is None:
            time.sleep(0.2)
            now = time.monotonic()
            if not memory_start and now - started > 10:
                memory_start = memory_kib(service.pid)
            if not controlled and now - started > 5:
                session.put(keys.setpoint(1, "depth"), json.dumps({"value": 16.0}))
                session.put(keys.setpoint(1, "pitch"), json.dumps({"value": 0.05}))
                session.put(keys.control(1), json.dumps({"enabled": True}))
                controlled = True
            if now >= next_outage:
                relay.paused.set()
                time.sleep(args.outage)
                relay.paused.clear()
                outages += 1
                next_outage = time.monotonic() + args.outage_every
        time.sleep(2.0)  # let the service drain
        memory_end = memory_kib(service.pid)
    finally:
        emulator_out = stop_process(emulator, 30)[0]
        service_out = stop_process(service, 30)[0]
        relay.stop()
        session.close()
    wall = time.monotonic() - started
    summary = last_json(service_out, "service")
    vehicle = summary.get("vehicles", {}).get("1", {})
    emulated = last_json(emulator_out, "emulator")
    counters = summary.get("counters", {})
    steps = emulated.get("steps", 0)
    samples = counters.get("samples", 0)
    faults = relay.snapshot()
    print(f"soak: {steps} emulated steps in {wall:.0f} s ({steps / wall:.0f}/s), "
          f"{outages} link outages of {args.outage:g} s")  # fmt: skip
    print(f"samples processed: {samples}; lost: {steps - samples} "
          f"({(steps - samples) / max(steps, 1):.2%}); incomplete steps "
          f"{counters.get('incomplete')}, identifier skipped "
          f"{vehicle.get('identifier', {}).get('depth', {}).get('skipped')}")  # fmt: skip
    print(f"relay: {faults.received} datagrams, dropped {faults.dropped}, duplicated "
          f"{faults.duplicated}, reordered {faults.reordered}; service link counters "
          f"{summary.get('link')}")  # fmt: skip
    print(f"commands sent: {vehicle.get('commands_sent')}, acks {vehicle.get('acks')}, "
          f"accepted by the emulator {emulated.get('commands_accepted')}")  # fmt: skip
    print(f"service memory: RSS {memory_start.get('VmRSS', 0) / 1024:.1f} MiB after 10 s, "
          f"{memory_end.get('VmRSS', 0) / 1024:.1f} MiB at the end, peak "
          f"{memory_end.get('VmHWM', 0) / 1024:.1f} MiB")  # fmt: skip
    print(f"log: {summary.get('log', {}).get('files')} file(s), "
          f"{summary.get('log', {}).get('records')} records, "
          f"{summary.get('log', {}).get('dropped')} dropped")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
