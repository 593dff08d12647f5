"""End-to-end throughput with the Foxglove live view on and a viewer connected, against the
same path without the live view, in the same run (the target: at least 80 %).

The path is ``serve``'s (``hil_service.builder.wire``: MAVLink datagrams → sample → both
identifiers → Zenoh publish → MCAP write); the viewer is the reference client
(``tests/foxglove_client/client.js``, ``@foxglove/ws-protocol``) subscribed to telemetry,
estimates and commands and validating every message, a real WebSocket on loopback. Runs
alternate (off, on, stalled, off, on, stalled, …; stalled: the viewer is stopped with
SIGSTOP once subscribed, a viewer that holds its connection and never reads again) so that
machine load hits all alike; medians and the ratios of medians are printed, with the live
view's own counters (offered, sent, dropped). A run with the live view ends when the live
view's process has taken everything offered (``LiveView.sync``). CPU per sample counts
every thread of this process and of the live view's (the SDK's server runs there), not the
viewer's (printed apart).

``--without-mavlink`` leaves the MAVLink channels out of the live view (it listens to the
publications only, ``without_mavlink``), to see what streaming them costs.

Run: .venv/bin/python benchmarks/bench_live_view.py [--samples N] [--repeats R]
     [--without-mavlink]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.bench_service import telemetry_datagrams  # noqa: E402
from hil_service.builder import open_recorder, wire  # noqa: E402
from hil_service.config import LogOptions, ServiceConfig  # noqa: E402
from hil_service.listeners import Listener, Notifier  # noqa: E402
from hil_service.listeners.zenoh_config import ZenohOptions, open_session  # noqa: E402
from hil_service.live.view import LiveAddress, LiveView  # noqa: E402
from hil_service.process_tuning import tune_for_service  # noqa: E402

CLIENT = ROOT / "tests" / "foxglove_client" / "client.js"
WARM_UP = 200  # samples fed before timing: the viewer subscribes to the channels they create


class _PublicationsOnly(Listener):
    def __init__(self, live: LiveView) -> None:
        self.live = live

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        self.live.on_publish(key, payload, data, reliable)


def without_mavlink(notifier: Notifier, live: LiveView) -> None:
    """The live view as a listener of the publications only (no MAVLink channels)."""
    notifier.remove_listener(live)
    notifier.add_listener(_PublicationsOnly(live))


def free_tcp_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_viewer(url: str) -> subprocess.Popen[str]:
    """The reference client, subscribed to telemetry, estimates and commands, validating
    every message (for up to 10⁹ messages or 600 s)."""
    return subprocess.Popen(
        [shutil.which("node") or "node", str(CLIENT), url, "1000000000", "600",
         "telemetry", "umodel", "command/ballast"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def one_run(
    warm: list[bytes],
    datagrams: list[bytes],
    live_on: bool,
    stalled: bool = False,
    mavlink: bool = True,
) -> dict[str, object]:
    """Throughput of the timed datagrams; with ``stalled``, the viewer is stopped (SIGSTOP)
    once subscribed: it holds its connection but never reads again."""
    config = ServiceConfig()
    session = open_session(ZenohOptions())
    with tempfile.TemporaryDirectory() as log_dir:
        recorder = open_recorder(config, LogOptions(directory=log_dir), {"bench": "1"})
        live = viewer = None
        if live_on:
            live = LiveView(LiveAddress("127.0.0.1", free_tcp_port())).start()
            viewer = start_viewer(live.url)
        wired = wire(config, session=session, recorder=recorder, live=live)
        tune_for_service()
        service = wired.service
        if not mavlink and live is not None:
            without_mavlink(wired.notifier, live)
        for data in warm:
            service.process_datagram(data)
        if live is not None:
            deadline = time.monotonic() + 30
            while not live.watched():  # the viewer has seen the channels and subscribed
                if time.monotonic() > deadline:
                    raise RuntimeError("the viewer did not subscribe within 30 s")
                time.sleep(0.05)
            if stalled and viewer is not None:
                viewer.send_signal(signal.SIGSTOP)
        before = service.source.assembler.counters.samples
        viewer_cpu = None if viewer is None else cpu_seconds(viewer.pid)
        # Every thread of this process (ours, Zenoh's) and of the live view's (the SDK's).
        cpu0 = time.process_time() + live_cpu_seconds(live)
        thread0 = time.thread_time()  # the service's thread alone (this one)
        sched0 = thread_sched()
        t0 = time.perf_counter()
        for data in datagrams:
            service.process_datagram(data)
        # The service's thread on the path alone (not its wait for the live view below).
        thread_cpu = time.thread_time() - thread0
        sched = [after - before for after, before in zip(thread_sched(), sched0, strict=True)]
        pending_at_end = 0 if live is None else live.status()["pending"]
        # The live view works behind the path: the run ends when its process has taken all.
        if live is not None and not live.sync():
            raise RuntimeError("the live view did not catch up within 60 s")
        elapsed = time.perf_counter() - t0
        cpu = time.process_time() + live_cpu_seconds(live) - cpu0
        if viewer is not None and viewer_cpu is not None:
            viewer_cpu = cpu_seconds(viewer.pid) - viewer_cpu
        samples = service.source.assembler.counters.samples - before
        status = live.status() if live is not None else None
        if status is not None:
            status["pending_when_the_path_ended"] = pending_at_end
        if viewer is not None:
            if stalled:
                viewer.send_signal(signal.SIGCONT)
            viewer.terminate()
            viewer.communicate(timeout=10)
        wired.close()
    return {
        "samples_per_s": samples / elapsed,
        "cpu_ms_per_sample": 1000 * cpu / samples,
        "thread_cpu_ms_per_sample": 1000 * thread_cpu / samples,
        # Time the service's thread was ready to run but waited for a core, and how often it
        # gave its core up itself (to wait for the GIL, mostly).
        "thread_runqueue_wait_ms_per_sample": sched[0] / 1e6 / samples,
        "thread_voluntary_switches": sched[1],
        "viewer_cpu_ms_per_sample": None if viewer_cpu is None else 1000 * viewer_cpu / samples,
        "live": status,
    }


def interleaved(
    warm: list[bytes], datagrams: list[bytes], chunk: int, per_step: int, mavlink: bool = True
) -> dict[str, Any]:
    """The service's CPU per sample without the live view and with it (a viewer connected),
    two services in this process fed the same datagrams in alternate chunks of ``chunk``
    samples (which of the two goes first alternates too): the machine's load changes from
    one moment to the next, and here it hits both alike. A chunk with the live view ends
    when its process has taken everything, so that its work is counted in its own chunk.
    CPU time of this process (every thread) and, for the chunks with it, of the live view's
    process; not wall time."""
    config = ServiceConfig()
    stack = []
    live = LiveView(LiveAddress("127.0.0.1", free_tcp_port())).start()
    viewer = start_viewer(live.url)
    log_dir = tempfile.TemporaryDirectory()
    try:
        services = []
        for name, with_live in (("off", None), ("on", live)):
            session = open_session(ZenohOptions())
            recorder = open_recorder(
                config, LogOptions(directory=f"{log_dir.name}/{name}"), {"bench": name}
            )
            wired = wire(config, session=session, recorder=recorder, live=with_live)
            stack.append(wired)
            if with_live is not None and not mavlink:
                without_mavlink(wired.notifier, with_live)
            for data in warm:
                wired.service.process_datagram(data)
            services.append(wired.service)
        deadline = time.monotonic() + 30
        while not live.watched():
            if time.monotonic() > deadline:
                raise RuntimeError("the viewer did not subscribe within 30 s")
            time.sleep(0.05)
        tune_for_service()
        size = chunk * per_step  # datagrams
        cpu: dict[str, list[float]] = {"off": [], "on": []}
        samples: dict[str, list[int]] = {"off": [], "on": []}
        for index, start in enumerate(range(0, len(datagrams), size)):
            part = datagrams[start : start + size]
            order = (("off", 0), ("on", 1)) if index % 2 == 0 else (("on", 1), ("off", 0))
            for name, which in order:
                service = services[which]
                before = service.source.assembler.counters.samples
                cpu0 = time.process_time() + live_cpu_seconds(live if which == 1 else None)
                for data in part:
                    service.process_datagram(data)
                if which == 1 and not live.sync():
                    raise RuntimeError("the live view did not catch up within 60 s")
                cpu[name].append(
                    time.process_time() + live_cpu_seconds(live if which == 1 else None) - cpu0
                )
                samples[name].append(service.source.assembler.counters.samples - before)
        ratios = [
            (off / max(n_off, 1)) / (on / max(n_on, 1))
            for off, on, n_off, n_on in zip(
                cpu["off"], cpu["on"], samples["off"], samples["on"], strict=True
            )
            if on > 0 and n_on > 0
        ]
        return {
            "chunks": len(ratios),
            "chunk_samples": chunk,
            "cpu_ms_per_sample_without": round(1000 * sum(cpu["off"]) / sum(samples["off"]), 4),
            "cpu_ms_per_sample_with_viewer": round(1000 * sum(cpu["on"]) / sum(samples["on"]), 4),
            "cpu_bound_ratio_with_to_without": round(
                (sum(cpu["off"]) / sum(samples["off"])) / (sum(cpu["on"]) / sum(samples["on"])), 3
            ),
            "median_ratio_per_chunk_pair": round(statistics.median(ratios), 3),
            "quartiles_ratio_per_chunk_pair": [
                round(q, 3) for q in statistics.quantiles(ratios, n=4)
            ],
            "live_view": live.status(),
        }
    finally:
        viewer.terminate()
        viewer.communicate(timeout=10)
        for wired in stack:
            wired.close()
        live.close()
        log_dir.cleanup()


def live_cpu_seconds(live: LiveView | None) -> float:
    """CPU time of the live view's process (its server, the SDK's threads), s; 0 without."""
    return 0.0 if live is None or live.pid is None else cpu_seconds(live.pid)


def thread_sched() -> tuple[int, int]:
    """(ns waited on a run queue, voluntary context switches) of the calling thread (Linux
    /proc; zeros elsewhere)."""
    task = f"/proc/self/task/{threading.get_native_id()}"
    try:
        with open(f"{task}/schedstat") as f:
            waited = int(f.read().split()[1])
        with open(f"{task}/status") as f:
            switches = next(
                int(line.split()[1]) for line in f if line.startswith("voluntary_ctxt_switches")
            )
    except (OSError, StopIteration, IndexError, ValueError):
        return 0, 0
    return waited, switches


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process (all its threads), s."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--without-mavlink", action="store_true", help="no MAVLink channels")
    parser.add_argument(
        "--interleaved",
        type=int,
        default=0,
        metavar="CHUNK",
        help="instead: CPU per sample without and with the live view, alternating every "
        "CHUNK samples between two services in this process",
    )
    args = parser.parse_args()
    if shutil.which("node") is None or not (CLIENT.parent / "node_modules").is_dir():
        print("needs node and `make foxglove-client`", file=sys.stderr)
        return 2
    everything = telemetry_datagrams(WARM_UP + args.samples)
    split = len(everything) * WARM_UP // (WARM_UP + args.samples)
    warm, datagrams = everything[:split], everything[split:]
    if args.interleaved:
        per_step = len(everything) // (WARM_UP + args.samples)  # datagrams a sample
        result = interleaved(warm, datagrams, args.interleaved, per_step, not args.without_mavlink)
        print(json.dumps(result))
        return 0
    off, on, stalled, live_status = [], [], [], []
    for _ in range(args.repeats):
        off.append(one_run(warm, datagrams, False))
        mavlink = not args.without_mavlink
        result = one_run(warm, datagrams, True, mavlink=mavlink)
        on.append(result)
        live_status.append(result["live"])
        result = one_run(warm, datagrams, True, stalled=True, mavlink=mavlink)
        stalled.append(result)
        live_status.append(result["live"])

    def rates(runs: list[dict[str, Any]]) -> list[float]:
        return [run["samples_per_s"] for run in runs]

    def cpu(runs: list[dict[str, Any]]) -> float:
        return statistics.median(run["cpu_ms_per_sample"] for run in runs)

    def thread_cpu(runs: list[dict[str, Any]]) -> float:
        return statistics.median(run["thread_cpu_ms_per_sample"] for run in runs)

    def median(runs: list[dict[str, Any]], what: str) -> float:
        field = {
            "wait": "thread_runqueue_wait_ms_per_sample",
            "switches": "thread_voluntary_switches",
        }
        return statistics.median(run[field[what]] for run in runs)

    pairs = [b / a for a, b in zip(rates(off), rates(on), strict=True)]
    report = {
        "samples": args.samples,
        "repeats": args.repeats,
        "mavlink_channels": not args.without_mavlink,
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
        "without_live_view_samples_per_s": [round(x) for x in rates(off)],
        "with_viewer_samples_per_s": [round(x) for x in rates(on)],
        "median_without": round(statistics.median(rates(off))),
        "median_with_viewer": round(statistics.median(rates(on))),
        "ratio_with_to_without": round(
            statistics.median(rates(on)) / statistics.median(rates(off)), 3
        ),
        # Each "with" against the "without" run just before it: load changes between pairs
        # cancel out.
        "ratio_per_pair": [round(x, 3) for x in pairs],
        "median_ratio_per_pair": round(statistics.median(pairs), 3),
        # CPU per sample of the service (every thread) and of the live view's process (the
        # SDK's): the throughput a core of its own gives, whatever the machine's load.
        "cpu_ms_per_sample_without": round(cpu(off), 4),
        "cpu_ms_per_sample_with_viewer": round(cpu(on), 4),
        "cpu_bound_ratio_with_to_without": round(cpu(off) / cpu(on), 3),
        # The service's thread alone: the throughput it has on a core of its own while
        # everything else (the live view's process, the viewer, Zenoh, the log) has the
        # other; on two otherwise idle cores, the bound of the whole-run ratio.
        "thread_cpu_ms_per_sample_without": round(thread_cpu(off), 4),
        "thread_cpu_ms_per_sample_with_viewer": round(thread_cpu(on), 4),
        "thread_bound_ratio_with_to_without": round(thread_cpu(off) / thread_cpu(on), 3),
        "thread_runqueue_wait_ms_per_sample_without": round(median(off, "wait"), 4),
        "thread_runqueue_wait_ms_per_sample_with_viewer": round(median(on, "wait"), 4),
        "thread_voluntary_switches_without": round(median(off, "switches")),
        "thread_voluntary_switches_with_viewer": round(median(on, "switches")),
        "viewer_cpu_ms_per_sample": round(
            statistics.median(run["viewer_cpu_ms_per_sample"] for run in on), 4
        ),
        "with_stalled_viewer_samples_per_s": [round(x) for x in rates(stalled)],
        "median_with_stalled_viewer": round(statistics.median(rates(stalled))),
        "ratio_stalled_to_without": round(
            statistics.median(rates(stalled)) / statistics.median(rates(off)), 3
        ),
        "cpu_bound_ratio_stalled_to_without": round(cpu(off) / cpu(stalled), 3),
        "live_view": live_status,
    }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
