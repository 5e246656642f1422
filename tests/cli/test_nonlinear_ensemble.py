"""`hood-decomp ensemble --nonlinear`: geometrically nonlinear members through the reduced model, in the store."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.cli import main
from hood_decomp.core.fe.ensemble import simulate_ensemble
from hood_decomp.core.fe.geometric import NonlinearSolver
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.io.ensemble_store import load_ensemble, store_info
from hood_decomp.io.model_files import load_model


def test_nonlinear_ensemble_is_stored_and_matches_the_full_solve(tiny_workspace, tmp_path) -> None:
    """Fails if `ensemble --nonlinear --range HINGE_Y=-0.5:0.5` does not write a store marked geometric-nonlinear
    with the range it was given, if its members differ from the full nonlinear solver's (NonlinearSolver on the same
    model: an independent iteration on the full mesh) by more than 0.05 mm, or if the full solve is not 0.3 mm from
    the linear members there (the check would not see the option doing nothing). On this 20 x 20 hood the reduced
    members are 0.0025-0.042 mm from the full solve where nonlinear minus linear reaches 0.47 mm (12 random members):
    the issue's 0.01 mm is not met (RESULTS.md, "A reduced nonlinear model")."""
    out = tmp_path / "nonlinear.h5"
    assert main(["ensemble", "--model", str(tiny_workspace.model), "--out", str(out), "--nonlinear",
                 "--range", "HINGE_Y=-0.5:0.5", "--validation", "4"]) == 0
    assert store_info(out)["physics"] == "geometric-nonlinear"
    assert store_info(tiny_workspace.ensemble)["physics"] == "linear"
    stored = load_ensemble(out, "validation")
    j = stored.names.index("HINGE_Y")
    assert (stored.lower[j], stored.upper[j]) == (-0.5, 0.5)
    assert np.all(np.abs(stored.commanded[:, j]) <= 0.5)
    model = load_model(tiny_workspace.model)
    solver = build_solver(model)
    full = NonlinearSolver(solver).members(stored.commanded)
    linear = simulate_ensemble(reduce_model(solver), stored.commanded, stored.rank, stored.lower, stored.upper)
    assert np.abs(stored.displacement - full.displacement).max() < 0.05
    assert np.abs(full.displacement - linear.displacement).max() > 0.3


@pytest.mark.parametrize("argv", [["--range", "HINGE_Y=0.5:-0.5"], ["--range", "NOPE=-1:1"],
                                  ["--range", "HINGE_Y=a:b"], ["--nonlinear", "--solver", "calculix"]])
def test_bad_nonlinear_options_end_in_one_error_line(tiny_workspace, tmp_path, capsys, argv) -> None:
    """Fails if a malformed --range (inverted, unknown label, not numbers) or --nonlinear with CalculiX does not end
    in exit status 2 with one error line naming the option, or writes the store."""
    out = tmp_path / "e.h5"
    try:
        status = main(["ensemble", "--model", str(tiny_workspace.model), "--out", str(out), *argv])
    except SystemExit as stop:
        status = stop.code
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert ": error: " in err[-1] and ("--range" in err[-1] or "--nonlinear" in err[-1])
    assert not out.exists()
