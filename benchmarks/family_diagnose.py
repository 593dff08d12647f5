"""Where the family plants above 1.1 × reference-only accrue their excess IAE.

Per plant (hold semantics, as ``experiment --scenario family``): the pipeline's and
reference-only's IAE per setpoint segment, split into the segment's first half (the
transient) and its second half (the steady state), and in the second half the mean error
(a bias) and its spread, beside the plant's disturbance. Prints the excess over
reference-only summed per group (never qualified / tripped / commanded throughout) and per
part, and whether the steady-state excess is bias or spread; then, for the plants with a
dead zone in their input map, how much of their excess accrued while the pipeline's input
sat inside the dead zone and reference-only's did not (the plant does not respond there,
and the loop creeps across it: docs/control.md, "Crossing a dead zone, and when after
a step the excess accrues").

    python benchmarks/family_diagnose.py --seeds 10 11 12 13 14 --plants 50 --save d.pkl

``--no-dead-zone`` runs the pipeline without the input dead zone chosen from the record
(docs/control.md, "An input dead zone, chosen from the record"), as the figures of "Crossing
a dead zone" were measured.

``--dead-zone-removed``: a bound, not a controller. The pipeline (choosing no dead zone) runs
on each plant with its dead zone taken out ahead of it (``DeadZoneRemoved``: what it
commands, u′, reaches the plant as u′ + δ·sign(u′) and it is told u′ back), scored against
reference-only on the true plant: what an input map that holds a dead zone exactly could
at most give.
"""

from __future__ import annotations

import argparse
import math
import pickle
from collections import defaultdict
from typing import Any

from hil_service.process_tuning import single_threaded_blas

single_threaded_blas()  # as every glider-hil command runs (before numpy loads)

import numpy as np  # noqa: E402

from hil_service.experiment.closed_loop import (  # noqa: E402
    ClosedLoopSettings,
    _drive,
    inverse_run,
    setpoint_schedule,
)
from hil_service.experiment.family_loop import HARM_LIMIT, levels, reference_only_controller  # noqa: E402
from hil_service.pipeline import PipelineSettings  # noqa: E402
from plant_emulator.family import FamilyPlantSpec, FamilyVehicle, draw_family  # noqa: E402
from plant_emulator.models import CHANNELS  # noqa: E402
from protocols.samples import TelemetrySample  # noqa: E402


def segments(setpoint: np.ndarray, start: int) -> list[tuple[int, int]]:
    changes = [k for k in range(start + 1, setpoint.size) if setpoint[k] != setpoint[k - 1]]
    starts = [start, *changes]
    return list(zip(starts, [*changes, setpoint.size], strict=True))


def plant_parts(y: np.ndarray, r: np.ndarray, start: int) -> dict[str, Any]:
    transient = steady = 0.0
    bias = spread = 0.0
    for k0, k1 in segments(r, start):
        mid = (k0 + k1) // 2
        e = y - r
        transient += float(np.sum(np.abs(e[k0:mid])))
        steady += float(np.sum(np.abs(e[mid:k1])))
        bias += abs(float(np.mean(e[mid:k1]))) * (k1 - mid)
        spread += float(np.std(e[mid:k1])) * (k1 - mid)
    return {"transient": transient, "steady": steady, "bias": bias, "spread": spread}


def dead_zone_width(spec: FamilyPlantSpec) -> float:
    """The half-width of the plant's dead zone (0 where its input map has none: only a
    Hammerstein plant's map acts on the input)."""
    return spec.input_map.dead_zone if spec.kind == "hammerstein" else 0.0


class DeadZoneRemoved(FamilyVehicle):
    """A family vehicle whose Hammerstein dead zones are taken out ahead of the plant: a
    command u′ reaches the actuator as u′ + δ·sign(u′), and the applied position u is
    reported as sign(u)·max(|u| − δ, 0)."""

    def __init__(self, depth: FamilyPlantSpec, pitch: FamilyPlantSpec, seed: int = 0):
        super().__init__(depth, pitch, seed)
        self.widths = {ch: dead_zone_width(spec) for ch, spec in self.specs.items()}

    def step(self, u_depth: float, u_pitch: float) -> TelemetrySample:
        wide = self.widths
        sample = super().step(_widen(u_depth, wide["depth"]), _widen(u_pitch, wide["pitch"]))
        return sample._replace(
            u_depth=_narrow(sample.u_depth, wide["depth"]),
            u_pitch=_narrow(sample.u_pitch, wide["pitch"]),
        )


def _widen(u: float, width: float) -> float:
    if width == 0.0 or u == 0.0 or not math.isfinite(u):
        return u
    return u + math.copysign(width, u)


def _narrow(u: float, width: float) -> float:
    return u if width == 0.0 else math.copysign(max(abs(u) - width, 0.0), u)


#: What every row of ``run`` holds; rows saved by an older version may lack some.
ROW_KEYS = frozenset({
    "seed", "spec", "group", "trips", "commanded", "first_command", "first_trip", "inv",
    "ref", "u_inv", "u_ref", "e_inv", "e_ref", "setpoint", "dead_zone_removed",
})  # fmt: skip


def run(
    seeds: list[int],
    plants: int,
    pipeline: PipelineSettings | None,
    dead_zone_removed: bool = False,
    no_dead_zone: bool = False,
) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        settings = ClosedLoopSettings(
            scenario="family", samples=2000, seed=seed, identify=800, step_every=300,
            oracle=False, neutral_after_identify=True,
        )  # fmt: skip
        for depth, pitch in draw_family(seed, plants):
            specs = {"depth": depth, "pitch": pitch}
            schedule = setpoint_schedule(settings, {ch: levels(specs[ch]) for ch in CHANNELS})
            reference_only = reference_only_controller(specs, schedule)

            vehicle = (DeadZoneRemoved if dead_zone_removed else FamilyVehicle)(depth, pitch, seed)
            chosen = pipeline
            if chosen is None and (dead_zone_removed or no_dead_zone):
                chosen = PipelineSettings(seed=seed, choose_dead_zone=False)
            inv = inverse_run(settings, vehicle, schedule, chosen)
            ref = _drive(settings, FamilyVehicle(depth, pitch, seed), schedule, reference_only)
            for i, ch in enumerate(CHANNELS):
                spec = specs[ch]
                start = settings.identify
                sup = inv.supervision[ch]
                modes = [m.split("/")[i] if m else "-" for m in inv.modes]
                first = next((j for j, m in enumerate(modes) if m not in ("-", "safe")), None)
                trip = next((j for j, m in enumerate(modes) if m == "safe"), None)
                rows.append({
                    "seed": seed, "spec": spec,
                    "group": "never qualified" if not sup["horizon_passed"]
                    else "tripped" if sup["trips"] else "commanded throughout",
                    "trips": sup["trips"], "commanded": sup["commanded"],
                    "first_command": first, "first_trip": trip,
                    "inv": plant_parts(inv.trace.y[ch], schedule[ch], start),
                    "ref": plant_parts(ref.y[ch], schedule[ch], start),
                    "u_inv": inv.trace.u[ch][start:].copy(),
                    "u_ref": ref.u[ch][start:].copy(),
                    "e_inv": (inv.trace.y[ch] - schedule[ch])[start:].copy(),
                    "e_ref": (ref.y[ch] - schedule[ch])[start:].copy(),
                    "setpoint": schedule[ch][start:].copy(),
                    "dead_zone_removed": dead_zone_removed,
                })  # fmt: skip
                assert rows[-1].keys() == ROW_KEYS, "ROW_KEYS names what a row holds"
    return rows


def total(parts: dict[str, float]) -> float:
    return parts["transient"] + parts["steady"]


def report(rows: list[dict[str, Any]]) -> None:
    above = [r for r in rows if total(r["inv"]) > HARM_LIMIT * total(r["ref"])]
    print(f"{len(above)} of {len(rows)} above {HARM_LIMIT}x reference-only")
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in above:
        groups[r["group"]].append(r)

    def excess(found: list[dict[str, Any]], part: str) -> float:
        return sum((r["inv"][part] - r["ref"][part]) / total(r["ref"]) for r in found)

    for name, found in groups.items():
        excess_t, excess_s = excess(found, "transient"), excess(found, "steady")
        bias, spread = excess(found, "bias"), excess(found, "spread")
        dist = defaultdict(int)
        for r in found:
            dist[r["spec"].disturbance] += 1
        print(
            f"  {name}: {len(found)}; excess / ref IAE summed: transient {excess_t:.2f}, "
            f"steady {excess_s:.2f} (bias {bias:.2f}, spread {spread:.2f}); {dict(dist)}"
        )
    since_step_report(above)
    spread_report(above)
    dead_zone_report(above)


def spread_report(above: list[dict[str, Any]]) -> None:
    """Of the plants above the limit commanded throughout, per disturbance: how many settle
    with an error that varies more than reference-only's (the spread of the segments'
    second halves above 1.1 × reference-only's): a loop that amplifies the disturbance."""
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for r in above:
        if r["group"] != "commanded throughout":
            continue
        kind = r["spec"].disturbance
        counts[kind][1] += 1
        counts[kind][0] += r["inv"]["spread"] > HARM_LIMIT * r["ref"]["spread"]
    parts = ", ".join(f"{kind} {n} of {m}" for kind, (n, m) in sorted(counts.items())) or "none"
    print(f"  commanded throughout, settling with more spread than reference-only: {parts}")


#: Samples since the last setpoint change, as the excess is binned by them.
SINCE_STEP_BINS = ((0, 10), (10, 30), (30, 60), (60, 150), (150, 300))


def since_step_report(above: list[dict[str, Any]]) -> None:
    """The excess over reference-only (per plant, ÷ its reference-only IAE, summed) by the
    samples since the last setpoint change: a loop's transient against its settling."""
    excess = [0.0] * len(SINCE_STEP_BINS)
    for r in above:
        e_inv, e_ref = np.abs(r["e_inv"]), np.abs(r["e_ref"])
        since = np.empty(e_inv.size, dtype=int)
        for k0, k1 in segments(r["setpoint"], 0):
            since[k0:k1] = np.arange(k1 - k0)
        for i, (a, b) in enumerate(SINCE_STEP_BINS):
            chosen = (since >= a) & (since < b)
            excess[i] += float(np.sum((e_inv - e_ref)[chosen])) / float(np.sum(e_ref))
    parts = ", ".join(
        f"{a}–{b}: {x:.2f}" for (a, b), x in zip(SINCE_STEP_BINS, excess, strict=True)
    )
    print(f"  excess / ref IAE summed, by samples since the setpoint changed: {parts}")


def has_dead_zone(row: dict[str, Any]) -> bool:
    return dead_zone_width(row["spec"]) > 0.0


def inside_dead_zone(row: dict[str, Any]) -> np.ndarray:
    """Samples where the pipeline's input is inside the plant's dead zone and
    reference-only's is not."""
    width = row["spec"].input_map.dead_zone
    return (np.abs(row["u_inv"]) < width) & (np.abs(row["u_ref"]) >= width)


def dead_zone_report(above: list[dict[str, Any]]) -> None:
    """Of the plants above the limit with a dead zone: the share of their excess IAE over
    reference-only that accrued while the pipeline's input sat inside it (and
    reference-only's did not), and those samples' share of the run."""
    # With the dead zones removed, the recorded inputs are the pipeline's own (u′).
    found = [r for r in above if has_dead_zone(r) and not r["dead_zone_removed"]]
    if not found:
        return
    excess = inside = samples = 0.0
    for r in found:
        e_inv, e_ref = np.abs(r["e_inv"]), np.abs(r["e_ref"])
        mask = inside_dead_zone(r)
        excess += float(np.sum(e_inv - e_ref)) / float(np.sum(e_ref))
        inside += float(np.sum((e_inv - e_ref)[mask])) / float(np.sum(e_ref))
        samples += float(np.mean(mask))
    print(
        f"  with a dead zone: {len(found)} of the {len(above)}; excess / ref IAE summed "
        f"{excess:.2f}, of it {inside:.2f} ({inside / excess:.0%}) while the pipeline's input "
        f"sat inside the dead zone and reference-only's did not "
        f"({samples / len(found):.1%} of their samples)"
    )


def load_rows(paths: list[str]) -> list[dict]:
    """The rows saved by ``--save`` in ``paths``; a clear exit for a file that is not one,
    or was saved by a version whose rows lack what the report reads."""
    rows: list[dict] = []
    for path in paths:
        try:
            with open(path, "rb") as f:
                loaded = pickle.load(f)
        except (OSError, EOFError, pickle.UnpicklingError) as error:
            raise SystemExit(f"{path}: not rows saved by --save ({error})") from error
        if not isinstance(loaded, list) or not all(isinstance(r, dict) for r in loaded):
            raise SystemExit(f"{path}: not rows saved by --save")
        missing = sorted(set().union(*(ROW_KEYS - row.keys() for row in loaded)))
        if missing:
            raise SystemExit(
                f"{path}: saved by an older family_diagnose.py, its rows without "
                f"{', '.join(missing)}: run it again with --save"
            )
        rows += loaded
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[10, 11, 12, 13, 14])
    parser.add_argument("--plants", type=int, default=50)
    parser.add_argument("--save")
    parser.add_argument("--load", nargs="+")
    parser.add_argument(
        "--dead-zone-removed",
        action="store_true",
        help="a bound: the pipeline on each plant with its dead zone taken out ahead of it "
        "(and no dead zone chosen from the record)",
    )
    parser.add_argument(
        "--no-dead-zone", action="store_true", help="no input dead zone chosen from the record"
    )
    args = parser.parse_args()
    if args.load:
        rows = load_rows(args.load)
    else:
        rows = run(args.seeds, args.plants, None, args.dead_zone_removed, args.no_dead_zone)
    report(rows)
    if args.save:
        with open(args.save, "wb") as f:
            pickle.dump(rows, f)


if __name__ == "__main__":
    main()
