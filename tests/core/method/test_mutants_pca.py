"""PCABasis details the main tests leave open: the length of the Fig. 8 curve, cut components, rtol, the pad
reactions and states carried by the components, refused inputs.

Written against the survivors of benchmarks/mutation.py. References are numpy's SVD of the centred ensemble, the
planted truth of tests/toy_models.py, or hand-made ensembles whose spectrum is known exactly.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hood_decomp.core.method.pca import CURVE_LENGTH, PCABasis
from hood_decomp.core.types import Ensemble
from hood_decomp.errors import BasisError
from tests.toy_models import full_factorial, make_ensemble, make_reduced_model, make_skin


@pytest.fixture(scope="module")
def linear():
    """Linear 4-parameter model, 81 members: the centred ensemble has rank exactly 4."""
    skin = make_skin(12, 8)
    model = make_reduced_model(skin, seed=1, n_pads=0)
    states, rank = full_factorial(4)
    return make_ensemble(model, states, rank)


@pytest.fixture(scope="module")
def pads():
    """4 bilateral parameters and 2 buffers (2 springs each), 729 members."""
    skin = make_skin(12, 8)
    model = make_reduced_model(skin, seed=5)
    states, rank = full_factorial(6)
    return make_ensemble(model, states, rank)


def tiny_ensemble(fields: np.ndarray) -> Ensemble:
    """An ensemble of the given (M, N) normal fields (3D part zero, no pads, one parameter)."""
    m, n = fields.shape
    return Ensemble(model_id="tiny", names=("P",), n_bilateral=1, lower=-np.ones(1), upper=np.ones(1),
                    commanded=np.arange(m, dtype=float)[:, None], effective=np.arange(m, dtype=float)[:, None],
                    contact_fraction=np.zeros((m, 0)), reactions=np.zeros((m, 0)), rank=np.full(m, -1),
                    normal_displacement=fields, displacement=np.zeros((m, n, 3)))


def test_curve_length_is_twenty_or_one_more_than_asked(linear):
    """Fails if the explained-variance curve (Fig. 8) does not hold max(K + 1, 20) values, capped at M (81 here)."""
    assert CURVE_LENGTH == 20
    for asked, length in ((1, 20), (10, 20), (19, 20), (20, 21), (25, 26), (79, 80), (80, 81), (81, 81), (200, 81)):
        basis = PCABasis(n_components=asked).fit(linear)
        assert basis.singular_values_.shape == (length,), asked
        assert basis.explained_variance_ratio_.shape == (length,), asked


def test_curve_values_are_the_leading_singular_values(linear):
    """Fails if the computed part of the spectrum is not the leading singular values of the centred ensemble."""
    x = linear.normal_displacement - linear.normal_displacement.mean(axis=0)
    reference = np.linalg.svd(x, compute_uv=False)
    basis = PCABasis(n_components=10).fit(linear)
    np.testing.assert_allclose(basis.singular_values_[:4], reference[:4], rtol=1e-10)
    np.testing.assert_allclose(basis.explained_variance_ratio_[:4], reference[:4] ** 2 / np.sum(reference**2),
                               rtol=1e-10)


@pytest.mark.parametrize("asked", [10, None])
def test_round_off_eigenvalues_are_not_negative(linear, asked):
    """Fails if round-off eigenvalues of a rank-4 ensemble come out negative or NaN (a variance is >= 0)."""
    basis = PCABasis(n_components=asked, explained_variance=None if asked else 1.0).fit(linear)
    assert np.all(np.isfinite(basis.singular_values_)) and np.all(basis.singular_values_ >= 0.0)
    assert np.all(basis.explained_variance_ratio_ >= 0.0)


def test_asking_exactly_the_supported_count_gives_no_note(linear):
    """Fails if asking for the 4 components a rank-4 ensemble supports is reported as a cut."""
    basis = PCABasis(n_components=4).fit(linear)
    assert basis.n_components_ == 4 and basis.notes_ == ()
    assert PCABasis(n_components=5).fit(linear).notes_ != ()


def test_zero_singular_values_are_cut_even_with_rtol_zero():
    """Fails if a component with a zero singular value is kept (its member weights would be 1/0): three members
    a, -a, 0 have one direction of variance; the member 0 equals the mean, so its row of the Gram matrix is exactly
    zero and so is one eigenvalue (rtol = 0 keeps round-off values above zero, not exact zeros)."""
    a = np.array([1.0, -2.0, 0.5, 4.0, 0.0, -1.0])
    basis = PCABasis(n_components=3, rtol=0.0).fit(tiny_ensemble(np.array([a, -a, 0 * a])))
    assert basis.singular_values_[-1] == 0.0
    assert basis.n_components_ <= 2
    assert np.all(np.isfinite(basis.components_)) and np.all(np.isfinite(basis.component_states_))
    np.testing.assert_allclose(np.abs(basis.components_[0]), np.abs(a) / np.linalg.norm(a), rtol=1e-12)


def test_an_ensemble_without_variance_is_refused(linear):
    """Fails if an ensemble whose members are all the same field is accepted (there is no component)."""
    same = np.repeat(linear.normal_displacement[:1], 4, axis=0)  # 4 members: their mean is exact
    with pytest.raises(BasisError, match="no variance"):
        PCABasis(n_components=2).fit(tiny_ensemble(same))
    with pytest.raises(BasisError, match="no variance"):
        PCABasis(n_components=2).fit(tiny_ensemble(np.zeros((4, 6))))


@pytest.mark.parametrize("fraction", [0.0, -0.1, 1.5])
def test_explained_variance_outside_zero_one_is_refused(linear, fraction):
    """Fails if an explained-variance target outside (0, 1] is accepted."""
    with pytest.raises(BasisError, match=r"explained_variance must be in \(0, 1\]"):
        PCABasis(n_components=None, explained_variance=fraction).fit(linear)


def test_explained_variance_one_is_accepted(linear):
    """Fails if the upper end 1.0 of (0, 1] is refused: it keeps every supported component (4 here)."""
    assert PCABasis(n_components=None, explained_variance=1.0).fit(linear).n_components_ == 4


def test_neither_count_nor_fraction_is_refused(linear):
    """Fails if a basis without n_components and explained_variance is built."""
    with pytest.raises(BasisError, match="give n_components or explained_variance"):
        PCABasis(n_components=None, explained_variance=None).fit(linear)


def test_member_reactions_and_states_are_reproduced(pads):
    """Fails if the pad reactions or the effective states do not ride along the same member combination: with every
    supported component, a member's own coefficients must give back its planted reactions and effective state
    (both are linear in the member's field for this toy model)."""
    basis = PCABasis(n_components=None, explained_variance=1.0).fit(pads)
    assert basis.component_reactions_.shape == (basis.n_components_, 2)
    coeff = (pads.normal_displacement - basis.mean_field_) @ basis.components_.T
    np.testing.assert_allclose(basis.mean_reaction_ + coeff @ basis.component_reactions_, pads.reactions,
                               atol=1e-8 * np.abs(pads.reactions).max())
    states = basis.mean_state_ + coeff @ basis.component_states_
    np.testing.assert_allclose(states[:, :4], pads.effective[:, :4], atol=1e-9)  # the bilateral states are linear
    np.testing.assert_allclose(basis.mean_reaction_, pads.reactions.mean(axis=0), rtol=1e-12)
    np.testing.assert_array_equal(basis.reaction_scale_, pads.reactions.max(axis=0))


def test_training_residual_is_the_worst_members_rms(linear):
    """Fails if training_residual_rms_ is not the largest per-member RMS of the rank-K reconstruction error
    (numpy SVD reference)."""
    x = linear.normal_displacement - linear.normal_displacement.mean(axis=0)
    u, s, vt = np.linalg.svd(x, full_matrices=False)
    for k in (1, 2, 3):
        resid = x - (u[:, :k] * s[:k]) @ vt[:k]
        expected = np.sqrt((resid**2).mean(axis=1)).max()
        assert PCABasis(n_components=k).fit(linear).training_residual_rms_ == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(PCABasis(n_components=3).fit(linear).gram_, np.eye(3), atol=1e-12)


def test_fitted_copies_of_the_ensemble(linear):
    """Fails if the basis does not keep the ensemble's names, bilateral count and ranges."""
    ranged = replace(linear, lower=np.array([-1.0, -2.0, -3.0, -4.0]), upper=np.array([1.0, 2.0, 3.0, 4.0]))
    basis = PCABasis(n_components=2).fit(ranged)
    assert basis.names_ == linear.names and basis.n_bilateral_ == linear.n_bilateral
    assert basis.model_id_ == linear.model_id
    np.testing.assert_array_equal(basis.lower_, [-1.0, -2.0, -3.0, -4.0])
    np.testing.assert_array_equal(basis.upper_, [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_allclose(basis.cumulative_explained_variance_, np.cumsum(basis.explained_variance_ratio_))


def test_default_parameters_are_the_papers():
    """Fails if the default is not 10 components (the paper's) with rtol 1e-7."""
    basis = PCABasis()
    assert (basis.n_components, basis.explained_variance, basis.rtol) == (10, None, 1e-7)


def test_a_small_ensemble_is_as_good_as_a_large_one(linear):
    """Fails if the basis depends on the units: the ensemble in metres (1e-3 x, total variance and largest singular
    value far below 1) must give the same component count and explained-variance ratios as in mm."""
    small = replace(linear, normal_displacement=1e-3 * linear.normal_displacement,
                    displacement=1e-3 * linear.displacement)
    x = small.normal_displacement - small.normal_displacement.mean(axis=0)
    s = np.linalg.svd(x, compute_uv=False)
    assert s[0] < 1.0 and np.sum(s**2) < 1.0
    basis = PCABasis(n_components=None, explained_variance=0.999).fit(small)
    assert basis.n_components_ == int(np.argmax(np.cumsum(s**2) / np.sum(s**2) >= 0.999)) + 1
    np.testing.assert_allclose(basis.explained_variance_ratio_[:4], s[:4] ** 2 / np.sum(s**2), rtol=1e-9)
    assert PCABasis(n_components=4).fit(small).n_components_ == 4
