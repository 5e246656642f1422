"""estimate_pca and the shared least-squares helpers against brute-force numpy references.

Written against the survivors of benchmarks/mutation.py. References: numpy's lstsq on the seen nodes with the textbook
covariance rss / (n - K) (A^T A)^-1, hand-made normal matrices whose conditioning is known, the planted reactions of
tests/toy_models.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.method.estimation import (
    LIFTED_REACTION_FRACTION,
    check_field,
    estimate_pca,
    solve_normal,
    valid_normal_matrix,
)
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.types import DisplacementField
from hood_decomp.errors import FieldError
from tests.toy_models import field_of, full_factorial, make_ensemble, make_reduced_model, make_skin


@pytest.fixture(scope="module")
def linear():
    skin = make_skin(20, 10)  # 200 nodes
    model = make_reduced_model(skin, seed=2, n_pads=0)
    states, rank = full_factorial(4)
    return skin, model, PCABasis(n_components=4).fit(make_ensemble(model, states, rank))


def lstsq_reference(basis: PCABasis, values: np.ndarray):
    """(coefficients, std of the parameter states) by numpy lstsq on the seen nodes and the textbook covariance."""
    seen = np.isfinite(values)
    a = basis.components_[:, seen].T
    coeff, *_ = np.linalg.lstsq(a, values[seen] - basis.mean_field_[seen], rcond=None)
    rss = float(np.sum((values[seen] - basis.mean_field_[seen] - a @ coeff) ** 2))
    cov = rss / (seen.sum() - a.shape[1]) * np.linalg.inv(a.T @ a)
    std = np.sqrt(np.diag(basis.component_states_.T @ cov @ basis.component_states_))
    return coeff, std


@pytest.mark.parametrize("n_unseen", [0, 1, 2, 60, 99, 100, 101, 150])
def test_estimate_matches_lstsq_on_the_seen_nodes(linear, n_unseen):
    """Fails if any count of unseen nodes (none, one, just below, at and above half of the 200) gives another fit or
    std than numpy's least squares on the seen nodes."""
    skin, model, basis = linear
    rng = np.random.default_rng(n_unseen)
    values = model.w0 + model.R @ np.array([0.3, -0.7, 0.2, 0.9]) + rng.normal(0.0, 0.05, skin.n_nodes)
    values[rng.permutation(skin.n_nodes)[:n_unseen]] = np.nan
    estimate = estimate_pca(basis, field_of(skin, values, 0.05))
    coeff, std = lstsq_reference(basis, values)
    np.testing.assert_allclose(estimate.values, basis.mean_state_ + coeff @ basis.component_states_, atol=1e-10)
    np.testing.assert_allclose(estimate.std, std, rtol=1e-9)
    np.testing.assert_allclose(estimate.reconstruction, basis.mean_field_ + coeff @ basis.components_, atol=1e-10)


def test_normal_matrix_over_the_seen_nodes_is_exact_when_the_unseen_part_dominates():
    """Fails if, with most nodes unseen, the normal matrix is formed as the full Gram matrix minus a much larger
    unseen part: the fields are 1e6 times larger where unseen, so the subtraction would lose ~12 digits."""
    rng = np.random.default_rng(0)
    fields = rng.normal(size=(3, 100))
    valid = np.zeros(100, dtype=bool)
    valid[:30] = True
    fields[:, ~valid] *= 1e6
    exact = fields[:, valid] @ fields[:, valid].T
    normal = valid_normal_matrix(fields, fields @ fields.T, valid)
    np.testing.assert_allclose(normal, exact, rtol=1e-12)
    # and with few nodes unseen the subtraction is exact enough, and all seen returns the Gram matrix itself
    small = rng.normal(size=(3, 100))
    gram = small @ small.T
    assert valid_normal_matrix(small, gram, np.ones(100, dtype=bool)) is gram
    some = np.ones(100, dtype=bool)
    some[[3, 50]] = False
    np.testing.assert_allclose(valid_normal_matrix(small, gram, some), small[:, some] @ small[:, some].T, rtol=1e-12)


def test_solve_normal_judges_singularity_by_angles_not_norms():
    """Fails if two independent fields of very different size (norm^2 1e8 and 1e-8) are called singular, or two
    fields 1e-14 apart in angle are not."""
    normal = np.array([[1e8, 0.5], [0.5, 1e-8]])
    coeff, inverse = solve_normal(normal, np.array([1e8, 1e-8]), "test")
    np.testing.assert_allclose(inverse, np.linalg.inv(normal), rtol=1e-9)
    np.testing.assert_allclose(coeff, np.linalg.solve(normal, [1e8, 1e-8]), rtol=1e-9)
    c = 1.0 - 1e-14
    with pytest.raises(FieldError, match="normal matrix is singular"):
        solve_normal(np.array([[1.0, c], [c, 1.0]]), np.ones(2), "test")
    with pytest.raises(FieldError, match="do not determine the things"):
        solve_normal(np.array([[4.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 9.0]]), np.ones(3), "things")
    with pytest.raises(FieldError, match="singular"):
        solve_normal(np.zeros((2, 2)), np.ones(2), "test")
    # a well-conditioned 3 x 3 matrix whose two largest eigenvalues differ a lot is fine
    well = np.diag([1.0, 1e-3, 1e-6])
    np.testing.assert_allclose(solve_normal(well, np.ones(3), "test")[0], [1.0, 1e3, 1e6], rtol=1e-12)


def test_a_zero_field_on_the_seen_nodes_is_singular():
    """Fails if a basis field that is zero on every seen node is not reported (its coefficient is undetermined)."""
    fields = np.array([[1.0, 2.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0]])
    valid = np.array([True, True, False, False])
    with pytest.raises(FieldError, match="singular"):
        solve_normal(valid_normal_matrix(fields, fields @ fields.T, valid), np.ones(2), "test")


def test_check_field_edges(linear):
    """Fails if a scalar field is not refused with a FieldError, or a coverage exactly at the minimum is refused."""
    skin, model, basis = linear
    with pytest.raises(FieldError, match="shape"):
        check_field(DisplacementField(basis.model_id_, np.float64(1.0), 1.0, 0.0), basis.model_id_, skin.n_nodes)
    with pytest.raises(FieldError, match="shape"):
        check_field(field_of(skin, np.zeros((skin.n_nodes, 1))), basis.model_id_, skin.n_nodes)
    values = model.w0.copy()
    values[50:] = np.nan  # 50 of 200 seen: coverage 0.25 exactly
    _, valid = check_field(field_of(skin, values), basis.model_id_, skin.n_nodes, min_coverage=0.25)
    assert valid.sum() == 50
    with pytest.raises(FieldError, match=r"coverage 0\.250 is below the minimum 0\.260"):
        check_field(field_of(skin, values), basis.model_id_, skin.n_nodes, min_coverage=0.26)


def test_pca_lifted_flags_follow_the_carried_reactions():
    """Fails if the paper's estimator does not report a pad lifted exactly when its reaction, carried through the
    component combination, is at most LIFTED_REACTION_FRACTION (1 %) of the largest ensemble reaction: checked on the
    training members, whose planted reactions the full basis reproduces."""
    assert LIFTED_REACTION_FRACTION == 0.01
    skin = make_skin(12, 8)
    model = make_reduced_model(skin, seed=5)
    states, rank = full_factorial(6)
    ensemble = make_ensemble(model, states, rank)
    basis = PCABasis(n_components=None, explained_variance=1.0).fit(ensemble)
    scale = ensemble.reactions.max(axis=0)
    lifted_seen = touching_seen = 0
    for i in range(0, ensemble.n_members, 7):
        estimate = estimate_pca(basis, field_of(skin, ensemble.normal_displacement[i]))
        expected = ensemble.reactions[i] <= 0.01 * scale
        # keep clear of the threshold, where round-off decides
        clear = np.abs(ensemble.reactions[i] - 0.01 * scale) > 1e-6 * scale
        np.testing.assert_array_equal(estimate.lifted[4:][clear], expected[clear])
        assert not estimate.lifted[:4].any()
        lifted_seen += int((expected & clear).sum())
        touching_seen += int((~expected & clear).sum())
    assert lifted_seen >= 10 and touching_seen >= 10


def test_std_with_one_degree_of_freedom(linear):
    """Fails if the residual variance of a fit with one more seen node than components (min_coverage 0) is not
    rss / 1, as numpy's least squares with the textbook covariance gives."""
    skin, model, basis = linear
    rng = np.random.default_rng(9)
    values = model.w0 + model.R @ np.array([0.3, -0.7, 0.2, 0.9]) + rng.normal(0.0, 0.05, skin.n_nodes)
    values[np.setdiff1d(np.arange(skin.n_nodes), [0, 37, 81, 122, 199])] = np.nan
    estimate = estimate_pca(basis, field_of(skin, values, 0.05), min_coverage=0.0)
    coeff, std = lstsq_reference(basis, values)
    np.testing.assert_allclose(estimate.values, basis.mean_state_ + coeff @ basis.component_states_, atol=1e-8)
    np.testing.assert_allclose(estimate.std, std, rtol=1e-6)
