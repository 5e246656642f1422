"""Fig. 11 of the paper on the geometrically nonlinear coarse hood-paper: the LOCK L & LOCK R interaction effect.

An ensemble over the two locks only (3 x 3 members, the other parameters 0), linear and nonlinear
(core/fe/geometric.py): 35 s for both tests in a suite run at load ~10, 160-300 s at load 15-18, hence ``slow``.
"""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble
from hood_decomp.core.fe.geometric import NonlinearSolver, nonlinear_ensemble
from hood_decomp.core.fe.hood_preset import build_preset
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.core.method.decomposition import decompose
from hood_decomp.core.method.hierarchical import HierarchicalBasis
from hood_decomp.core.types import DisplacementField, Ensemble

LOCKS = ("LOCK_L", "LOCK_R")
pytestmark = pytest.mark.slow


def _locks_only(ensemble: Ensemble, columns: list[int]) -> Ensemble:
    """The same members seen as an ensemble over the two lock parameters only (the others are 0 in every member)."""
    return Ensemble(model_id=ensemble.model_id, names=LOCKS, n_bilateral=2, lower=ensemble.lower[columns],
                    upper=ensemble.upper[columns], commanded=ensemble.commanded[:, columns],
                    effective=ensemble.effective[:, columns], contact_fraction=ensemble.contact_fraction,
                    reactions=ensemble.reactions, rank=ensemble.rank, normal_displacement=ensemble.normal_displacement,
                    displacement=ensemble.displacement)


@pytest.fixture(scope="module")
def lock_study():
    model = build_preset("hood-paper", "coarse")
    solver = build_solver(model)
    columns = [model.names.index(name) for name in LOCKS]
    commanded2, rank = factorial_plan(model.lower[columns], model.upper[columns])
    commanded = np.zeros((len(commanded2), len(model.names)))
    commanded[:, columns] = commanded2
    nonlinear = NonlinearSolver(solver, tolerance=1e-5, contraction=0.2)
    ensembles = {
        "nonlinear": nonlinear_ensemble(nonlinear, commanded, rank, model.lower, model.upper),
        "linear": simulate_ensemble(reduce_model(solver), commanded, rank, model.lower, model.upper),
    }
    return model, columns, nonlinear, {k: _locks_only(e, columns) for k, e in ensembles.items()}


def test_lock_pair_interaction_needs_geometric_nonlinearity(lock_study) -> None:
    """Fails if the linear hood-paper's LOCK_L & LOCK_R members stop lying within 0.1 mm of the loads' and single
    effects' span (no interaction effect, as the issue-21 study found) or if the nonlinear members do not leave that
    span by more than 0.1 mm (the greedy must then add LOCK_L & LOCK_R)."""
    _, _, _, ensembles = lock_study
    bases = {name: HierarchicalBasis(0.1).fit(e) for name, e in ensembles.items()}
    assert bases["linear"].effect_names_ == ("LOADS", "LOCK_L", "LOCK_R")
    assert "LOCK_L & LOCK_R" in bases["nonlinear"].effect_names_


def test_fig11_field_keeps_the_lock_pair_effect(lock_study) -> None:
    """Fails if decomposing a LOCK_L + LOCK_R field of the nonlinear hood (0.8 and -0.7 mm, as Fig. 11; a new FE
    solve, not an ensemble member) drops the LOCK_L & LOCK_R effect in coarsening or reconstructs the field worse
    than 0.002 mm RMS. Its partial displacement is not asserted: it is 0.058 mm where the planted interaction
    u(a_L + a_R) - u(a_L) - u(a_R) + u0 peaks at 0.15 mm: between the grid's states the contact-born interaction
    is not in the span of the effect's two fields (best fit leaves 0.053 mm), so the issue's 5 % is met at the grid's
    corner (next test), not here (RESULTS.md)."""
    model, columns, nonlinear, ensembles = lock_study
    basis = HierarchicalBasis(0.1).fit(ensembles["nonlinear"])
    state = np.zeros((1, len(model.names)))
    state[0, columns] = (0.8, -0.7)
    field = DisplacementField(model.model_id, nonlinear.members(state).normal_displacement[0], 1.0, float("nan"))
    decomposition = decompose(basis, field)
    assert "LOCK_L & LOCK_R" in {effect.name for effect in decomposition.effects}
    assert decomposition.reconstruction_rms < 0.002


def test_lock_pair_effect_carries_the_planted_interaction_at_a_corner(lock_study) -> None:
    """Fails if the LOCK_L & LOCK_R effect's partial displacement (eq. 6) in the decomposition of a LOCK_L +1,
    LOCK_R -1 field differs from the planted interaction |u(a_L + a_R) - u(a_L) - u(a_R) + u0| (3D, four new
    nonlinear solves, differenced here, not through the basis) by more than 5 % of its peak, or if coarsening drops
    the effect. The paper's difference field alone gives the effect only the part outside the single effects' span
    (0.16 of 0.21 mm here); between the grid's states (Fig. 11's 0.8 / -0.7) no two-field effect follows this
    contact-born interaction (RESULTS.md)."""
    model, columns, nonlinear, ensembles = lock_study
    basis = HierarchicalBasis(0.1).fit(ensembles["nonlinear"])
    states = np.zeros((4, len(model.names)))
    states[0, columns], states[1, columns[0]], states[2, columns[1]] = (1.0, -1.0), 1.0, -1.0
    u = nonlinear.members(states).displacement
    planted = np.linalg.norm(u[0] - u[1] - u[2] + u[3], axis=1)
    field = DisplacementField(model.model_id, nonlinear.members(states[:1]).normal_displacement[0], 1.0,
                              float("nan"))
    effects = {effect.name: effect for effect in decompose(basis, field).effects}
    assert planted.max() > 0.15
    difference = np.abs(effects["LOCK_L & LOCK_R"].partial_displacement - planted).max()
    assert difference < 0.05 * planted.max()
