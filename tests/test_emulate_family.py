"""``emulate --family SEED:INDEX`` and ``--reboot-at``: the family vehicle behind the glider's
interface, which plants fit the glider's telemetry, and the options' clear errors."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from plant_emulator import cli
from plant_emulator.family import FamilyVehicle, draw_vehicle
from plant_emulator.plant import FamilyPlant, wire_bounds


def _run(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    return cli.run(parser.parse_args(list(argv)))


def test_a_family_plant_steps_as_the_family_vehicle_at_any_period():
    depth, pitch = draw_vehicle(0, 3)
    reference = FamilyVehicle(depth, pitch, 0)
    plant = FamilyPlant(0, 3, period=0.01, system_id=7)
    for k in range(200):
        u = ((k // 17) % 3 - 1.0, 0.5 - (k // 29) % 2)
        want, got = reference.step(*u), plant.step(*u)
        assert (got.depth, got.pitch, got.u_depth, got.u_pitch) == (
            want.depth, want.pitch, want.u_depth, want.u_pitch,
        )  # fmt: skip
        assert got.time_boot_ms == 10 * k and got.system_id == 7
    assert plant.applied_inputs() == (got.u_depth, got.u_pitch)
    assert FamilyPlant(0, 3).config.period == depth.period  # its own period by default


def test_wire_bounds_name_an_output_the_glider_telemetry_cannot_carry():
    depth, pitch = draw_vehicle(0, 3)
    assert wire_bounds(depth) == "" and wire_bounds(pitch) == ""
    assert "outside ±π" in wire_bounds(dataclasses.replace(pitch, offset=10.0))
    assert "m, outside" in wire_bounds(dataclasses.replace(depth, offset=-100.0))
    assert wire_bounds(dataclasses.replace(depth, integrator=True))  # it ramps


@pytest.mark.parametrize(
    "argv, message",
    [
        (("--family", "0"), "SEED:INDEX"),
        (("--family", "0:x"), "SEED:INDEX"),
        (("--family", "0:-1"), "index must be ≥ 0"),
        (("--reboot-at", "5"), "--reboot-at needs a periodic profile"),
        (("--profile", "ardusub", "--reboot-at", "0"), "--reboot-at must be a plant step ≥ 1"),
        (("--vehicles", "3", "--family", "0:3"), "--family and --reboot-at run one vehicle"),
    ],
)
def test_bad_family_and_reboot_options_are_refused_clearly(argv, message, capsys):
    assert _run("--connect", "udpout:127.0.0.1:9", *argv) == 2
    assert message in capsys.readouterr().err
