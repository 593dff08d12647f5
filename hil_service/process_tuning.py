"""Interpreter settings for a process that runs the per-sample path for a long time.

``serve`` and ``replay`` call :func:`tune_for_service` once, after start-up; the benchmarks
call it too, so that they measure the path as those commands run it.

* Switch interval 0.5 ms: the recorder's thread must not hold the GIL for the default
  5 ms while a telemetry datagram waits, so a short interval bounds the control path's wait.
* ``gc.freeze()`` after start-up: the modules and objects that exist then (numpy, scipy,
  Zenoh, pymavlink's dialect: hundreds of thousands of objects) live as long as the process,
  and without the freeze every full collection traverses them again.
* A larger first-generation threshold: each sample allocates a few hundred container
  objects (decoded messages, payload dicts, log records queued for the writer thread), and
  many outlive a 700-allocation generation, so at the default threshold they are
  traversed again and again on their way to the old generation.
"""

from __future__ import annotations

import gc
import os
import sys
from collections.abc import Callable

SWITCH_INTERVAL_S = 0.0005
GC_THRESHOLDS = (10_000, 10, 10)


def tune_for_service() -> None:
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


def one_cpu_child() -> tuple[int, Callable[[], None]]:
    """(cpu, preexec_fn) that pins a child process and every thread it will start (Zenoh's
    runtime included) to the first CPU this process may use: "on one core", literally."""
    cpu = min(os.sched_getaffinity(0))
    return cpu, lambda: os.sched_setaffinity(0, {cpu})
