"""`hood-decomp estimate --coarsen` (issue 15: the paper's coarsening of the input field). Truth: the setting given to
`simulate` (a direct FE solve, not the bases' reduced model)."""

from __future__ import annotations

import json

from hood_decomp.cli import main

SETTING = {"HINGE_X": 0.3, "LOCK_L": -0.2}


def test_a_coarsened_estimate_of_a_simulated_field_finds_its_setting(tiny_workspace, tmp_path, capsys):
    """A field `simulate` solved: estimated on a quarter of the nodes it returns the setting (the FE solve and the
    reduced model agree to round-off: measured 1e-9 mm) and says how many nodes it fitted; auto keeps every node of
    this small skin; with the three components a stride is refused in one line, exit 2."""
    field = tmp_path / "f.vtu"
    assert main(["simulate", "--model", str(tiny_workspace.model), "--set",
                 ",".join(f"{k}={v}" for k, v in SETTING.items()), "--out", str(field)]) == 0
    results = {}
    for coarsen in ("2", "auto"):
        out = tmp_path / f"{coarsen}.json"
        assert main(["estimate", "--bases", str(tiny_workspace.bases), "--field", str(field), "--coarsen", coarsen,
                     "--json", str(out)]) == 0
        results[coarsen] = json.loads(out.read_text())
    coarse, auto = results["2"], results["auto"]
    for name, value in SETTING.items():
        assert abs(coarse["parameters_mm"][name] - value) < 1e-6
    assert coarse["coarsening"]["stride"] == 2
    # the test ran on the kept nodes (not only the JSON's own account of the stride)
    assert coarse["within_model_test"]["effective_samples"] < auto["within_model_test"]["effective_samples"] / 3
    assert coarse["coarsening"]["fitted_nodes"] < coarse["coarsening"]["nodes"] / 3
    assert auto["coarsening"] == {"stride": 1, "fitted_nodes": auto["coarsening"]["nodes"],
                                  "nodes": coarse["coarsening"]["nodes"]}
    capsys.readouterr()
    assert main(["estimate", "--bases", str(tiny_workspace.bases), "--field", str(field), "--coarsen", "2",
                 "--components", "xyz"]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "not coarsened" in error
