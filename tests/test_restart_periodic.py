"""A vehicle reboot on a periodic (ArduSub-style) profile: the sampler tells a reboot (its
clock steps back) from an outage (it jumps ahead), the next sample carries the reboot, and
the pipeline stops commanding until the model passes the horizon test on data after it,
as it does when a lockstep vehicle's timestamps step back."""

from __future__ import annotations

from hil_service.sources.sampler import SamplerConfig, StreamSampler
from tests.harm_rig import Loop, spec

PERIOD = 0.1
SIGNALS = ("depth", "pitch", "u_depth", "u_pitch")


def _sampler() -> StreamSampler:
    return StreamSampler(SamplerConfig(PERIOD, {s: (0.5,) for s in SIGNALS}))


def _stream(sampler: StreamSampler, start_s: float, seconds: float) -> list:
    """Every signal every 50 ms of the vehicle's clock from ``start_s``: the complete ticks."""
    ticks = []
    for i in range(round(seconds / 0.05)):
        ms = round((start_s + 0.05 * i) * 1000)
        readings = [(name, 0, 1.0 + i * 1e-3) for name in SIGNALS]
        ticks += [t for t in sampler.observe(readings, ("ms32", ms)) if t.values is not None]
    return ticks


def test_the_sampler_counts_a_step_back_as_a_reboot_and_a_jump_ahead_as_an_outage():
    sampler = _sampler()
    first = _stream(sampler, 600.0, 20.0)
    rebooted = _stream(sampler, 3.0, 20.0)  # the clock starts again 3 s after boot
    assert sampler.counters.segments == 1 and sampler.counters.reboots == 1
    assert rebooted[0].t > first[-1].t  # the time line goes on across it
    _stream(sampler, 60.0, 20.0)  # nothing for 37 s of the vehicle's clock: an outage
    assert sampler.counters.segments == 2 and sampler.counters.reboots == 1
    assert sampler.counters.reasons["clock jump"] > 0
    assert sampler.counters.as_dict()["reboots"] == 1


def test_a_marked_reboot_while_commanding_stops_until_the_horizon_test_passes_again():
    loop = Loop(spec(), spec())
    loop.run(1500, {"depth": None, "pitch": None})
    loop.run(300, {"depth": 15.8, "pitch": None})
    assert loop.modes[-1].startswith(("newton", "fallback"))
    loop.reboot_marked()
    loop.run(600, {"depth": 15.8, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    after = loop.modes[1800:]
    assert not after[0], "commanded on the reboot's own sample"
    resumed = next(i for i, m in enumerate(after) if m)
    assert resumed >= min(depth.settings.burn_in, depth.controller.horizon), resumed
    assert "model does not predict over the horizon (depth" in loop.reasons[1820]
    # The timestamps never stepped back: only the mark told the pipeline.
    assert loop.pipeline.gaps.restarts == 0 and depth.restarts == 1
    assert after[-1].startswith(("newton", "fallback"))


def test_the_assembler_marks_the_first_sample_after_a_reboot_and_only_that_one():
    from hil_service.sources.periodic_assembler import ProfileAssembler
    from tests.test_profile_assembler import PROFILE, stream

    assembler = ProfileAssembler(PROFILE)
    first = [s for m in stream(1, 20.0) for s in assembler.add_all(m)]
    again = [s for m in stream(1, 5.0) for s in assembler.add_all(m)]  # from 1 s after boot
    assert first and again and not any(s.restarted for s in first)
    assert [s.restarted for s in again] == [True] + [False] * (len(again) - 1)
    assert again[0].time_boot_ms > first[-1].time_boot_ms  # the time line goes on
    counted = assembler.counters_for(1)
    assert (counted.restarts, counted.reboots) == (1, 1)
