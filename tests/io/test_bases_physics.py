"""Bases files with the FE model's responses behind its physical factors (/physics, issue 15 / 21).

Truth: bases built in memory from the same ensemble and model with the responses computed from the model
(core.loop.calibration.model_physics), never written; the file's group is written by `hood-decomp bases --model` and
read back by load_bases (its 3D parts only when a three-component fit first reads them).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from hood_decomp.cli import main
from hood_decomp.core.fe.ensemble import simulate_setting
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.core.loop.calibration import model_physics, one_at_a_time
from hood_decomp.core.method.bases import build_bases, estimate_field
from hood_decomp.core.types import DisplacementField
from hood_decomp.io.bases import load_bases, save_bases
from hood_decomp.io.ensemble_store import load_ensemble, load_skin
from hood_decomp.io.fields import read_field, write_field
from hood_decomp.io.model_files import load_model

FIVE = ("compliance (Young's modulus)", "sheet thickness", "pad stiffness", "pad preload", "gas-spring force")
THREE = ("compliance (Young's modulus)", "pad stiffness", "pad preload")


@pytest.fixture(scope="module")
def files(tiny_workspace, tmp_path_factory):
    """(a `bases --model` file, the same bases written without /physics, the in-memory bases with the responses)."""
    ws = tiny_workspace
    root = tmp_path_factory.mktemp("bases_physics")
    written = root / "with.h5"
    assert main(["bases", "--ensemble", str(ws.ensemble), "--model", str(ws.model), "--out", str(written)]) == 0
    model = load_model(ws.model)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    memory = build_bases(load_ensemble(ws.ensemble), load_skin(ws.ensemble), reduced, 10)
    memory = dataclasses.replace(memory, physics=model_physics(model, reduced, solver))
    without = root / "without.h5"
    save_bases(without, dataclasses.replace(memory, physics=None))
    return written, without, memory


def test_a_bases_file_estimates_with_the_five_factors_of_the_in_memory_bases(files, tiny_workspace):
    """Fails if `bases --model` does not store the model's physical responses, if load_bases reads them other than
    written (a stacked array sliced wrong, the 3D parts of another array), or if the 3D parts are read on load: the
    file's estimates of a simulated field must consider the five factors with model effects equal to the in-memory
    bases' to 1e-9 mm (normal) and 1e-6 of the largest effect (xyz: its 3D parts are stored float32); and the group
    must not change the file's bases_id."""
    written, without, memory = files
    loaded = load_bases(written, mapped=True)
    assert loaded.physics is not None and loaded.physics.load_3d is not None  # 3D parts left unread on load
    assert loaded.physics.gas_w3.shape[0] == 0
    field, _ = read_field(tiny_workspace.field)
    for components, tolerance in (("normal", 0.0), ("xyz", 1e-6)):
        expected = estimate_field(memory, field, components=components)
        found = estimate_field(loaded, field, components=components)
        assert found.model_factors == expected.model_factors == FIVE
        assert np.abs(expected.model_effects[FIVE.index("sheet thickness")]).max() > 1e-4  # the factor moves values
        atol = max(1e-9, tolerance * np.abs(expected.model_effects).max())
        np.testing.assert_allclose(found.model_effects, expected.model_effects, rtol=0, atol=atol)
        np.testing.assert_allclose(found.values, expected.values, rtol=0, atol=1e-9)
    assert loaded.physics.with_3d().gas_w3.shape == (field.normal_displacement.size, 3)
    with h5py.File(written, "r") as a, h5py.File(without, "r") as b:
        assert "physics" in a and "physics" not in b
        assert a.attrs["bases_id"] == b.attrs["bases_id"]


def test_estimate_json_reports_the_five_factors_and_a_file_without_the_group_three(files, tiny_workspace, tmp_path):
    """Fails if `estimate --json` from a `bases --model` file does not report the five factors, or a file without
    /physics does not load (physics None) with the three it always considered."""
    written, without, _ = files
    for path, factors in ((written, FIVE), (without, THREE)):
        out = tmp_path / f"{path.stem}.json"
        assert main(["estimate", "--bases", str(path), "--field", str(tiny_workspace.field), "--json", str(out)]) == 0
        assert set(json.loads(out.read_text())["model_factors_mm"]) == set(factors)
    assert load_bases(without).physics is None


def _calibration_entries(ws, tmp_path: Path) -> Path:
    """CAL.json of 13 one-at-a-time fields of the workspace's model with its pads 25 % stiffer (0.005 mm noise)."""
    model = load_model(ws.model)
    solver = build_solver(model)
    skin = load_skin(ws.ensemble)
    rng = np.random.default_rng(21)
    entries = []
    for j, setting in enumerate(one_at_a_time(len(model.names))):
        chosen = {label: float(v) for label, v in zip(model.names, setting, strict=True) if v}
        values = simulate_setting(solver, chosen).normal_displacement + rng.normal(0, 0.005, skin.n_nodes)
        write_field(tmp_path / f"e{j}.vtu", skin, DisplacementField(skin.model_id, values, 1.0, 0.005))
        entries.append({"field": f"e{j}.vtu", "setting": chosen})
    (tmp_path / "cal.json").write_text(json.dumps(entries))
    return tmp_path / "cal.json"


def test_calibrate_takes_the_responses_from_the_file(files, tiny_workspace, tmp_path, monkeypatch):
    """Fails if `calibrate` on a file with /physics computes the responses again (model_physics is made to fail
    here), or calibrates otherwise than from the same bases without the group (which computes them from the
    model): the same factors, their std and the same leave-one-out RMS."""
    import hood_decomp.core.loop.calibration as calibration

    written, without, _ = files
    cal = _calibration_entries(tiny_workspace, tmp_path)
    common = ["calibrate", "--model", str(tiny_workspace.model), "--cal", str(cal)]
    assert main([*common, "--bases", str(without), "--out", str(tmp_path / "from_model.h5")]) == 0

    def computed(*_args, **_kwargs):
        raise AssertionError("calibrate computed the physical responses the bases file holds")

    monkeypatch.setattr(calibration, "model_physics", computed)
    assert main([*common, "--bases", str(written), "--out", str(tmp_path / "from_file.h5")]) == 0
    records = [json.loads(load_bases(tmp_path / name).calibration) for name in ("from_model.h5", "from_file.h5")]
    for key in ("factors", "factor_std", "loo_rms_mm", "rank"):
        assert records[1][key] == pytest.approx(records[0][key], rel=1e-9, abs=1e-12), key
