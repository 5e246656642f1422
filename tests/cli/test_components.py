"""`hood-decomp estimate --components xyz` (issue 21): the three displacement components of a simulated field.

Truth: the setting given to `simulate` (a direct FE solve, not the bases' reduced model)."""

from __future__ import annotations

import json

import pytest

from hood_decomp.cli import main

SETTING = {"HINGE_X": 0.3, "LOCK_L": -0.2}


@pytest.fixture(scope="module")
def simulated(tiny_workspace, tmp_path_factory):
    field = tmp_path_factory.mktemp("components") / "f.vtu"
    assert main(["simulate", "--model", str(tiny_workspace.model), "--set",
                 ",".join(f"{k}={v}" for k, v in SETTING.items()), "--out", str(field)]) == 0
    return field


@pytest.mark.parametrize("method", ["contact", "pca"])
def test_estimate_fits_the_three_components_simulate_wrote(tiny_workspace, simulated, tmp_path, capsys, method):
    out = tmp_path / "e.json"
    assert main(["estimate", "--bases", str(tiny_workspace.bases), "--field", str(simulated), "--method", method,
                 "--components", "xyz", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["components"] == "xyz" and result["method"] == method
    if method == "contact":  # exact on its own model's fields: the FE solve and the reduced model agree to round-off
        for name, value in SETTING.items():
            assert result["parameters_mm"][name] == pytest.approx(value, abs=1e-6)
    default = tmp_path / "n.json"
    assert main(["estimate", "--bases", str(tiny_workspace.bases), "--field", str(simulated), "--method", method,
                 "--json", str(default)]) == 0
    normal = json.loads(default.read_text())
    assert normal["components"] == "normal"
    # the skin's test on each of the three components: three times its smooth modes, the level from the residual
    assert result["within_model_test"]["dof"] == 3 * normal["within_model_test"]["dof"] > 0
    assert result["within_model_test"]["noise_source"] == "residual"


def test_xyz_on_a_field_without_three_components_is_one_named_error(tiny_workspace, tmp_path, capsys):
    from dataclasses import replace

    from hood_decomp.core.types import FieldErrorModel
    from hood_decomp.io.bases import load_bases
    from hood_decomp.io.fields import read_field, write_field

    skin = load_bases(tiny_workspace.bases).skin
    field, _ = read_field(tiny_workspace.field, skin)
    assert field.displacement is not None
    normal_only, stated = tmp_path / "normal.vtu", tmp_path / "stated.vtu"
    write_field(normal_only, skin, replace(field, displacement=None))
    write_field(stated, skin, replace(field, error_model=FieldErrorModel.stated(0.01, skin.n_nodes)))
    cases = ((["--field", str(normal_only)], "no 3D displacement"),
             (["--scan", str(tiny_workspace.scan)], "'scan' error model states the errors of its normal values"),
             (["--field", str(stated)], "'stated' error model states the errors of its normal values"))
    for inputs, message in cases:
        code = main(["estimate", "--bases", str(tiny_workspace.bases), *inputs, "--components", "xyz"])
        err = capsys.readouterr().err
        assert code == 2, err
        errors = [line for line in err.splitlines() if line.startswith("hood-decomp estimate: error:")]
        assert len(errors) == 1 and message in errors[0], err
