"""Per-dive identification of field data: the two-input U-model beside the others."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from hil_service.mcap.reader import LogReader
from hil_service.offline.field.evaluate import Arrays, identify_dives
from hil_service.offline.field.report import field_arrays

DATA = Path(__file__).parent / "data" / "field"


def _arrays(source: Path, out: Path) -> Arrays:
    done = subprocess.run(
        [sys.executable, "-m", "hil_service.cli", "import", str(source), "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
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
    assert glide.trace is not None and set(glide.parameters) >= {"beta_0", "gamma", "structure"}
    # The measured pitch is what the single-input U-model lacks: on both slices the
    # two-input model's free run is at least 10 points better.
    assert models["dynamic"].fit is not None
    assert glide.fit > models["dynamic"].fit + 10.0
    assert glide.fit > models["persistence"].fit  # type: ignore[operator]


def test_alternate_split_holds_out_every_other_dive(arrays: Arrays) -> None:
    depth = identify_dives(arrays, split="alternate")[0]
    dives = sorted(depth.train_dives + depth.held_out)
    assert depth.train_dives == dives[0::2] and depth.held_out == dives[1::2]
    with pytest.raises(ValueError, match="unknown split"):
        identify_dives(arrays, split="random")
