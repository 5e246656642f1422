"""The interaction map (core.method.interactions) against known truth and independent FE solves."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import simulate_setting
from hood_decomp.core.method.interactions import interaction_map
from hood_decomp.errors import BasisError
from hood_decomp.plots.method import plot_interaction_map
from tests.toy_models import interacting_ensemble, make_skin


def test_planted_interaction_is_found_and_nothing_else() -> None:
    """Fails if the map mixes up pairs or signs, or reports interaction in a part that responds additively: the toy
    ensemble is linear plus field g * LOCK_L * LOCK_R (and a triple term that is zero on rank-2 members), so the
    LOCK_L/LOCK_R cells must equal max|g| with the sign s_L s_R g at the reported node, every other cell 0."""
    skin = make_skin()
    _, ensemble, terms = interacting_ensemble(skin)
    g = terms[0][1]
    found = interaction_map(ensemble)
    L, R = found.names.index("LOCK_L"), found.names.index("LOCK_R")
    for si, s_l in enumerate((1.0, -1.0)):
        for sj, s_r in enumerate((1.0, -1.0)):
            assert found.peak_mm[L, R, si, sj] == pytest.approx(np.abs(g).max(), rel=1e-9)
            assert found.peak_mm[R, L, sj, si] == found.peak_mm[L, R, si, sj]
            node = found.node[L, R, si, sj]
            assert found.signed_mm[L, R, si, sj] == pytest.approx(s_l * s_r * g[node], rel=1e-9)
    others = found.pair_peak_mm.copy()
    others[L, R] = others[R, L] = 0.0
    assert np.nanmax(others) < 1e-12 and np.all(np.isnan(np.diag(found.pair_peak_mm)))
    assert found.rows()[0][0:4:2] == ("LOCK_L", "LOCK_R")


def test_missing_member_is_named() -> None:
    """Fails if an ensemble without the needed rank-2 member gives a map instead of an error naming the member."""
    skin = make_skin()
    _, ensemble, _ = interacting_ensemble(skin)
    missing = int(np.flatnonzero((ensemble.commanded[:, 2] == 1.0) & (ensemble.commanded[:, 3] == -1.0)
                                 & (ensemble.rank == 2))[0])
    keep = np.arange(ensemble.n_members) != missing
    cut = replace(ensemble, commanded=ensemble.commanded[keep], normal_displacement=ensemble.normal_displacement[keep])
    with pytest.raises(BasisError, match="no member LOCK_L=1, LOCK_R=-1"):
        interaction_map(cut)


def test_hood_maps_against_fe_solves(coarse_hood, coarse_hood_paper, tmp_path) -> None:
    """Fails if the map of a hood ensemble differs from the second difference of four independent forward solves
    (simulate_setting: a fresh reduction and contact solve per setting), or if the interaction stops being what
    contact makes it: pairs of a lock and a buffer interact (both presets, > 0.3 mm on the coarse hood), rigid buffers
    (hood-paper) more than preloaded pads (hood), and HINGE_X, which barely moves the front, interacts with nothing
    above 0.02 mm. Writes the heat map."""
    for case, pair in ((coarse_hood_paper, ("LOCK_L", "BUFFER_L")), (coarse_hood, ("HINGE_Y", "LOCK_R"))):
        found = interaction_map(case.ensemble)
        i, j = (found.names.index(n) for n in pair)
        u0 = simulate_setting(case.solver, {}).normal_displacement
        for si, sj in ((0, 0), (1, 1), (0, 1)):
            s_i, s_j = (1.0, -1.0)[si], (1.0, -1.0)[sj]
            u = {key: simulate_setting(case.solver, setting).normal_displacement for key, setting in (
                ("ij", {pair[0]: s_i, pair[1]: s_j}), ("i", {pair[0]: s_i}), ("j", {pair[1]: s_j}))}
            second = u["ij"] - u["i"] - u["j"] + u0
            assert found.peak_mm[i, j, si, sj] == pytest.approx(np.abs(second).max(), abs=1e-9)
    paper, default = interaction_map(coarse_hood_paper.ensemble), interaction_map(coarse_hood.ensemble)
    lock, buffer, hinge_x = (paper.names.index(n) for n in ("LOCK_L", "BUFFER_L", "HINGE_X"))
    assert paper.pair_peak_mm[lock, buffer] > default.pair_peak_mm[lock, buffer] > 0.3
    assert np.nanmax(paper.pair_peak_mm[hinge_x]) < 0.02 and np.nanmax(default.pair_peak_mm[hinge_x]) < 0.02
    path = plot_interaction_map(paper, tmp_path / "map.png", "hood-paper coarse")
    assert path.stat().st_size > 10_000
