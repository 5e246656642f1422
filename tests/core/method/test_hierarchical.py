"""Hierarchical basis (Fig. 5) on synthetic ensembles with known interaction effects."""

import logging
from dataclasses import replace

import numpy as np
import pytest

from hood_decomp.core.method.decomposition import reconstruct_members
from hood_decomp.core.method.hierarchical import HierarchicalBasis
from hood_decomp.errors import BasisError
from tests.toy_models import (
    full_factorial,
    interacting_ensemble,
    make_ensemble,
    make_reduced_model,
    make_skin,
    plain_hierarchical,
    random_states,
)

SINGLES = ("LOADS", "HINGE_X", "HINGE_Y", "LOCK_L", "LOCK_R")


@pytest.fixture(scope="module")
def interacting():
    skin = make_skin()
    return (skin, *interacting_ensemble(skin))


def test_finds_exactly_the_true_interactions(interacting, caplog):
    _, _, ensemble, _ = interacting
    with caplog.at_level(logging.INFO, logger="hood_decomp.core.method.hierarchical"):
        basis = HierarchicalBasis(epsilon=0.01).fit(ensemble)
    lines = [r.getMessage() for r in caplog.records if r.name == "hood_decomp.core.method.hierarchical"]
    assert basis.effect_names_ == (*SINGLES, "LOCK_L & LOCK_R", "HINGE_X & HINGE_Y & LOCK_L")
    assert basis.effect_parameters(5) == ("LOCK_L", "LOCK_R")
    assert basis.effect_parameters(6) == ("HINGE_X", "HINGE_Y", "LOCK_L")
    assert basis.effect_rank_.tolist() == [0, 1, 1, 1, 1, 2, 3]
    assert lines and "rank 2" in lines[1]
    # It stopped: the last trace step of the last rank is within epsilon and every member is reconstructed within it.
    assert basis.trace_[-1, 2] <= 0.01 and np.all(basis.rank_max_error_ <= 0.01)
    error = np.abs(reconstruct_members(basis, ensemble.normal_displacement) - ensemble.normal_displacement).max()
    assert error <= 0.01


def test_matches_the_plain_refitting_loop(interacting):
    """Incremental projections give the same effects as refitting every member from scratch (paper stack)."""
    _, _, ensemble, _ = interacting
    basis = HierarchicalBasis(epsilon=0.01).fit(ensemble)
    names, _ = plain_hierarchical(ensemble.normal_displacement, ensemble.commanded, ensemble.rank,
                                  ensemble.names, 0.01)
    assert list(basis.effect_names_[1:]) == names


def test_validation_members_between_samples_are_reconstructed(interacting):
    """Random states (not in the ensemble) of the same physics lie in the span of the found effects."""
    _, model, _, terms = interacting
    basis = HierarchicalBasis(epsilon=0.01).fit(interacting[2])
    validation = make_ensemble(model, random_states(model, 20, seed=9), None, terms)
    error = np.abs(reconstruct_members(basis, validation.normal_displacement) - validation.normal_displacement)
    assert error.max() < 1e-9


def test_linear_ensemble_needs_no_interaction_and_coarse_epsilon_skips_small_ones(interacting):
    _, model, ensemble, terms = interacting
    states, rank = full_factorial(4)
    linear = make_ensemble(model, states, rank)
    singles = HierarchicalBasis(epsilon=1e-6).fit(linear)
    assert singles.effect_names_ == SINGLES
    # Outside the span of the single effects the pair term leaves 0.24 mm, the 3-way term 0.11 mm (both measured by
    # projecting the known terms): at epsilon 0.15 mm only the pair interaction is needed.
    q = np.linalg.qr(singles.fields_[singles.independent_].T)[0]
    left = [np.abs(field - q @ (q.T @ field)).max() for _, field, _ in terms]
    assert left[0] > 0.15 > left[1]
    assert HierarchicalBasis(epsilon=0.15).fit(ensemble).effect_names_ == (*SINGLES, "LOCK_L & LOCK_R")


def test_3d_fields_and_states_follow_the_member_weights(interacting):
    skin, _, ensemble, _ = interacting
    basis = HierarchicalBasis(epsilon=0.01).fit(ensemble)
    np.testing.assert_allclose(np.einsum("fnj,nj->fn", basis.fields_3d_, skin.normals), basis.fields_, atol=1e-10)
    # Rank-1 fields are u(+-e_p) - u0: their states are +-e_p.
    pair = basis.effect_fields_[basis.effect_names_.index("HINGE_Y")]
    np.testing.assert_allclose(basis.field_states_[pair], [[0, 1, 0, 0], [0, -1, 0, 0]], atol=1e-12)
    # An interaction's inverse partner of a pure product term adds no new direction.
    pair = basis.effect_fields_[basis.effect_names_.index("LOCK_L & LOCK_R")]
    assert basis.independent_[pair].tolist() == [True, False]


def test_bad_input_is_refused(interacting):
    _, _, ensemble, _ = interacting
    with pytest.raises(BasisError, match="full-factorial"):
        HierarchicalBasis().fit(replace(ensemble, rank=np.full(ensemble.n_members, -1)))
    with pytest.raises(BasisError, match="epsilon"):
        HierarchicalBasis(epsilon=0.0).fit(ensemble)
    keep = ensemble.rank != 1
    with pytest.raises(BasisError, match="rank-1 member"):
        HierarchicalBasis().fit(replace(ensemble, normal_displacement=ensemble.normal_displacement[keep],
                                        commanded=ensemble.commanded[keep], rank=ensemble.rank[keep]))


def test_pad_contact_ensemble_builds_and_stays_within_epsilon():
    """With buffers (a piecewise-linear contact response) the greedy loop still ends within epsilon."""
    skin = make_skin(16, 12)
    model = make_reduced_model(skin, seed=5)
    states, rank = full_factorial(6)
    ensemble = make_ensemble(model, states, rank)
    basis = HierarchicalBasis(epsilon=0.01).fit(ensemble)
    assert np.all(basis.rank_max_error_ <= 0.01)
    error = np.abs(reconstruct_members(basis, ensemble.normal_displacement) - ensemble.normal_displacement).max()
    assert error <= 0.01 + 1e-9
