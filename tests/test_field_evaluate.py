"""Per-dive identification of field data: the two-input U-model beside the others."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil_service.cli.processes import run_verb
from hil_service.mcap.reader import LogReader
from hil_service.offline.field.evaluate import Arrays, identify_dives
from hil_service.offline.field.report import field_arrays

DATA = Path(__file__).parent / "data" / "field"


def _arrays(source: Path, out: Path) -> Arrays:
    done = run_verb("import", str(source), "-o", str(out), timeout=120)
    assert done.returncode == 0, done.stderr
    reader = LogReader(out)
    for _ in reader.messages({"glider/1/telemetry"}):
        pass
    return field_arrays(out, reader.config()["field"])


@pytest.fixture(scope="module", params=["seaglider-sg542", "seaexplorer-sea035"])
def arrays(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Arrays:
    return _arrays(DATA / request.param, tmp_path_factory.mktemp("field") / "log.mcap")


def test_glide_u_model_scored_with_the_others_and_beats_the_single_input_one(
    arrays: Arrays,
) -> None:
    depth = identify_dives(arrays)[0]
    models = {m.model: m for m in depth.models}
    assert list(models) == [
        "persistence",
        "rls-arx",
        "dynamic",
        "glide-u",
        "steady-glide",
        "steady-glide-buoyancy-only",
    ]
    glide = models["glide-u"]
    assert glide.fit is not None and glide.skill is not None and glide.k_step_nmse is not None
    assert glide.trace is not None and set(glide.parameters) >= {"beta_1", "structure"}
    # The parameters are those of the structure chosen: the buoyancy input's β₀ and γ, or
    # the flight model's v₀ and c_p beneath the steady-glide input's polynomial.
    feature = glide.parameters["structure_choice"]["feature"]
    own = {"beta_0", "gamma"} if feature == "buoyancy" else {"v0", "c_p"}
    assert set(glide.parameters) >= own
    assert glide.parameters["structure"].startswith(feature)
    # The measured pitch is what the single-input U-model lacks.
    assert models["dynamic"].fit is not None
    assert glide.fit > models["dynamic"].fit
    assert glide.fit > models["persistence"].fit  # type: ignore[operator]


def test_the_steady_glide_input_of_degree_one_free_runs_as_the_flight_model(
    arrays: Arrays,
) -> None:
    # Trained online (RLS) where the flight model is fitted by least squares, on the same
    # training dives with the flight model's v₀ and c_p: the same free run.
    options = {"feature": "steady-glide", "degree": 1, "drift": False}
    depth = identify_dives(arrays, glide_options=options)[0]
    models = {m.model: m for m in depth.models}
    glide, flight = models["glide-u"], models["steady-glide"]
    assert glide.parameters["v0"] == flight.parameters["v0"]
    assert glide.parameters["c_p"] == flight.parameters["c_p"]
    assert glide.parameters["beta_1"] == pytest.approx(
        -flight.parameters["k"] * arrays.period, rel=0.01
    )
    assert glide.fit == pytest.approx(flight.fit, abs=0.5)


def test_alternate_split_holds_out_every_other_dive(arrays: Arrays) -> None:
    depth = identify_dives(arrays, split="alternate")[0]
    dives = sorted(depth.train_dives + depth.held_out)
    assert depth.train_dives == dives[0::2] and depth.held_out == dives[1::2]
    with pytest.raises(ValueError, match="unknown split"):
        identify_dives(arrays, split="random")
