"""The asynchronous-stream sampler: wraps, reboots, late and reordered messages.

Every stream here carries its own stamp (vehicle seconds since boot) as its value, so a
sample's value says exactly which reading it used: it must be stamped at or before the
sample's vehicle time and be within the staleness limit, or the sample must be incomplete.
"""

from __future__ import annotations

import itertools
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil_service.sources.sampler import SamplerConfig, StreamSampler

PERIOD = 0.1
US32_SPAN = (1 << 32) / 1e6  # s, 71.6 min


def config(**changes) -> SamplerConfig:
    values = {
        "period": PERIOD,
        "staleness": {"depth": (0.2, 0.5), "pitch": (0.2,), "u_depth": (0.2,), "climb": (0.2,)},
        "optional": frozenset({"climb"}),
    }
    values.update(changes)
    return SamplerConfig(**values)


def stream_messages(
    start: float, end: float, boot: float, rng: random.Random, pressure: bool = True
) -> list[tuple[float, tuple, tuple | None]]:
    """(send time, readings, clock) of ArduSub-like streams: ATTITUDE (ms32) at 10 Hz,
    SCALED_PRESSURE2 (ms32) at 10 Hz, SERVO_OUTPUT_RAW (us32) at 10 Hz, VFR_HUD unstamped at
    4 Hz; each message stamped when sent, with jitter. ``boot``: when the vehicle booted."""
    out = []
    streams = [("pitch", 0.1, "ms32"), ("u_depth", 0.1, "us32"), ("hud", 0.25, None)]
    if pressure:
        streams.append(("depth", 0.1, "ms32"))
    for name, interval, kind in streams:
        t = start + rng.uniform(0, interval)
        while t < end:
            uptime = t - boot
            if kind == "ms32":
                clock = ("ms32", int(uptime * 1000) & 0xFFFFFFFF)
                stamp = int(uptime * 1000) / 1000
            elif kind == "us32":
                clock = ("us32", int(uptime * 1e6) & 0xFFFFFFFF)
                stamp = int(uptime * 1e6) / 1e6
            else:
                clock, stamp = None, None
            if name == "hud":
                readings = (("depth", 1, -1.0), ("climb", 0, 0.5))  # value checked apart
            else:
                readings = ((name, 0, stamp),)
            out.append((t, readings, clock))
            t += interval * rng.uniform(0.9, 1.1)
    out.sort(key=lambda item: item[0])
    return out


def deliver(sampler: StreamSampler, messages, rng: random.Random, shuffle: float = 0.0):
    """Feed messages in arrival order: each is delayed by up to ``shuffle`` s."""
    arrivals = sorted(messages, key=lambda m: m[0] + rng.uniform(0, shuffle))
    ticks = []
    for _, readings, clock in arrivals:
        ticks.extend(sampler.observe(readings, clock))
    return ticks


def check_ticks(ticks, sampler: StreamSampler) -> None:
    times = [tick.t for tick in ticks]
    assert all(b > a for a, b in itertools.pairwise(times)), "t must increase"
    for tick in ticks:
        if tick.values is None:
            assert tick.reason
            continue
        for name in ("pitch", "u_depth"):
            used = tick.values[name]
            assert tick.vehicle_t - 0.2 - 1e-6 <= used <= tick.vehicle_t + 1e-6, (name, tick)
        depth = tick.values["depth"]
        assert depth == -1.0 or tick.vehicle_t - 0.2 - 1e-6 <= depth <= tick.vehicle_t + 1e-6
    counters = sampler.counters
    assert counters.samples == sum(t.values is not None for t in ticks)


def test_steady_streams_make_one_sample_per_period():
    rng = random.Random(1)
    sampler = StreamSampler(config())
    ticks = deliver(sampler, stream_messages(100.0, 160.0, 0.0, rng), rng, shuffle=0.02)
    check_ticks(ticks, sampler)
    expected = 60.0 / PERIOD
    assert len(ticks) >= expected - 3
    assert sampler.counters.samples / expected >= 0.95
    assert sampler.counters.fallbacks == {}  # SCALED_PRESSURE2 present: no VFR_HUD depth


def test_depth_falls_back_to_vfr_hud_when_pressure_is_absent():
    rng = random.Random(2)
    sampler = StreamSampler(config())
    ticks = deliver(sampler, stream_messages(5.0, 25.0, 0.0, rng, pressure=False), rng)
    check_ticks(ticks, sampler)
    complete = [t for t in ticks if t.values is not None]
    assert len(complete) >= 0.95 * len(ticks) > 0
    assert all(t.values["depth"] == -1.0 for t in complete)
    assert sampler.counters.fallbacks["depth"] == len(complete)


def test_a_silent_stream_makes_samples_incomplete_with_the_reason():
    rng = random.Random(3)
    sampler = StreamSampler(config())
    messages = stream_messages(0.0, 20.0, 0.0, rng)
    # ATTITUDE stops after 10 s; the others go on.
    messages = [m for m in messages if not (m[1][0][0] == "pitch" and m[0] > 10.0)]
    ticks = deliver(sampler, messages, rng)
    check_ticks(ticks, sampler)
    late = [t for t in ticks if t.vehicle_t > 10.5]
    assert late and all(t.values is None and t.reason == "pitch stale" for t in late)
    assert sampler.counters.reasons["pitch stale"] == sum(t.reason == "pitch stale" for t in ticks)
    assert all(t.values is not None for t in ticks if t.vehicle_t < 10.0)


def test_microsecond_clock_wrap_does_not_disturb_sampling():
    rng = random.Random(4)
    sampler = StreamSampler(config())
    start = US32_SPAN - 20.0  # the µs clock wraps 20 s in
    ticks = deliver(sampler, stream_messages(start, start + 40.0, 0.0, rng), rng, 0.02)
    check_ticks(ticks, sampler)
    assert sampler.counters.segments == 0
    assert sampler.counters.samples / (40.0 / PERIOD) >= 0.95
    assert any(t.vehicle_t > US32_SPAN + 1 for t in ticks if t.values is not None)


def test_reboot_restarts_the_clock_and_sampling_goes_on():
    rng = random.Random(5)
    sampler = StreamSampler(config())
    before = stream_messages(500.0, 530.0, 0.0, rng)
    after = stream_messages(535.0, 565.0, 532.0, rng)  # rebooted at 532: uptime from 3 s
    ticks = deliver(sampler, before, rng) + deliver(sampler, after, rng)
    check_ticks(ticks, sampler)
    assert sampler.counters.segments == 1
    after_reboot = [t for t in ticks if t.values is not None and t.vehicle_t < 100]
    assert len(after_reboot) >= 0.9 * 30 / PERIOD


def test_a_lone_corrupt_stamp_is_discarded():
    rng = random.Random(6)
    sampler = StreamSampler(config())
    messages = stream_messages(10.0, 30.0, 0.0, rng)
    messages.insert(len(messages) // 2, (20.0, (("pitch", 0, 9999.0),), ("ms32", 9_999_000)))
    ticks = deliver(sampler, messages, rng)
    check_ticks(ticks, sampler)
    assert sampler.counters.segments == 0
    assert sampler.counters.discarded == 1
    assert sampler.counters.samples / (20.0 / PERIOD) >= 0.95


def test_bad_values_and_unknown_signals_are_counted():
    sampler = StreamSampler(config())
    assert sampler.observe([("depth", 0, 1.0)], None) == []  # no clock yet
    sampler.observe([("pitch", 0, float("nan")), ("roll", 0, 1.0)], ("ms32", 1000))
    assert sampler.counters.as_dict()["unstamped"] == 1
    assert sampler.counters.invalid == 1
    assert sampler.counters.unknown == 1
    with pytest.raises(ValueError):
        SamplerConfig(period=0.0, staleness={})
    with pytest.raises(ValueError):
        sampler.observe([], ("ns16", 1))


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    uptime=st.floats(1.0, 2 * US32_SPAN),
    reboots=st.lists(st.floats(3.0, 40.0), max_size=3),
    shuffle=st.floats(0.0, 0.3),
)
def test_any_wraps_reboots_and_reordering(seed, uptime, reboots, shuffle):
    """Whatever the clocks do, sampling never stops, t increases, values are never stale."""
    rng = random.Random(seed)
    sampler = StreamSampler(config())
    ticks = []
    start, boot = uptime, 0.0
    for length in [*reboots, 20.0]:
        first = start - boot  # the run's first vehicle time
        ticks += deliver(sampler, stream_messages(start, start + length, boot, rng), rng, shuffle)
        boot = start + length + 1.0  # reboot: the next run's uptime starts near 1 s
        start = boot + 1.0
    check_ticks(ticks, sampler)
    # The last stretch (20 s, after every reboot) is sampled: reordering beyond the delay
    # may cost samples but never stops sampling.
    last = [t for t in ticks[-int(20 / PERIOD) :] if t.values is not None and t.vehicle_t >= first]
    assert len(last) >= (0.9 if shuffle <= PERIOD / 2 else 0.5) * 17 / PERIOD
