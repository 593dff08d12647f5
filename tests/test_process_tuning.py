"""The long-running processes' interpreter settings: garbage collection on a schedule."""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import threading
import weakref
from pathlib import Path

import pytest

from hil_service.process_tuning import BLAS_THREAD_VARIABLES, Collector

ROOT = Path(__file__).resolve().parent.parent


class Node:
    def __init__(self) -> None:
        self.other: Node | None = None


def test_a_reference_cycle_is_reclaimed_with_automatic_collection_off() -> None:
    reclaimed = threading.Event()
    was_enabled = gc.isenabled()
    gc.disable()
    collector = None
    try:
        first, second = Node(), Node()
        first.other, second.other = second, first
        weakref.finalize(first, reclaimed.set)
        del first, second
        assert not reclaimed.is_set()  # only a collection can free a cycle
        collector = Collector(0.02)
        assert reclaimed.wait(10), "the collector never reclaimed the cycle"
        # The cycle is freed inside the collector's gc.collect(), before it counts the
        # collection: stopped (its thread joined), the count includes that one.
        collector.stop()
        assert collector.collections >= 1
    finally:
        if collector is not None:
            collector.stop()
        if was_enabled:
            gc.enable()


@pytest.mark.parametrize("period", [0.0, -1.0, float("nan")])
def test_a_period_that_cannot_run_is_refused(period: float) -> None:
    with pytest.raises(ValueError, match="positive"):
        Collector(period)


def test_a_tuned_process_freezes_its_start_up_and_collects_only_on_the_schedule() -> None:
    probe = (
        "import gc, threading\n"
        "from hil_service.process_tuning import tune_for_service\n"
        "tune_for_service(); tune_for_service()\n"
        "names = [t.name for t in threading.enumerate()]\n"
        "print(gc.isenabled(), gc.get_freeze_count() > 1000, names.count('gc-collector'))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["False", "True", "1"]


BLAS_THREADS = """
import ctypes, sys
from hil_service.cli import main
try:
    main(["experiment", "--help"])  # a verb whose modules load numpy
except SystemExit:
    pass
import numpy  # noqa: F401
for line in open("/proc/self/maps"):
    path = line.split()[-1]
    if "openblas" in path.lower() and ".so" in path:
        lib = ctypes.CDLL(path)
        for name in ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_",
                     "openblas_get_num_threads"):
            if hasattr(lib, name):
                print(getattr(lib, name)(), file=sys.stderr)
                raise SystemExit(0)
print("no OpenBLAS", file=sys.stderr)
"""


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one core: BLAS runs on one thread anyway")
@pytest.mark.parametrize(("given", "expected"), [(None, "1"), ("2", "2")])
def test_a_command_runs_blas_on_one_thread_unless_the_user_set_a_count(given, expected) -> None:
    # numpy's OpenBLAS starts a thread per core; on small matrices its threads only spin on
    # the cores the service and the emulator need. A count the user set stands.
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    run = subprocess.run(
        [sys.executable, "-c", BLAS_THREADS], cwd=ROOT, env=env, capture_output=True,
        text=True, timeout=60,
    )  # fmt: skip
    found = run.stderr.strip().splitlines()[-1]
    if found == "no OpenBLAS":
        pytest.skip("numpy is not linked to OpenBLAS here")
    assert found == expected, run.stderr
