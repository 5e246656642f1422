"""PCA basis (section 3.1.2) on synthetic ensembles with known truth."""

import numpy as np
import pytest
from sklearn.decomposition import PCA

from hood_decomp.core.method.estimation import estimate_pca
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.errors import BasisError
from tests.toy_models import field_of, full_factorial, make_ensemble, make_reduced_model, make_skin, random_states


@pytest.fixture(scope="module")
def linear():
    """A linear (no pads) 4-parameter model: its centred ensemble has rank exactly 4."""
    skin = make_skin()
    model = make_reduced_model(skin, seed=1, n_pads=0)
    states, rank = full_factorial(4)
    return skin, model, make_ensemble(model, states, rank)


def test_exact_recovery_from_known_coefficients(linear):
    skin, _, ensemble = linear
    basis = PCABasis(n_components=4).fit(ensemble)
    coeff = np.array([0.3, -1.2, 0.05, 2.0])
    values = basis.mean_field_ + coeff @ basis.components_
    estimate = estimate_pca(basis, field_of(skin, values))
    np.testing.assert_allclose(estimate.values, basis.mean_state_ + coeff @ basis.component_states_, atol=1e-12)
    np.testing.assert_allclose(estimate.reconstruction, values, atol=1e-12)
    assert estimate.residual_rms < 1e-12


def test_states_between_sample_points_are_recovered(linear):
    """The basis is built on {-1, 0, 1}; random states in between come out right (the model is linear)."""
    skin, model, ensemble = linear
    basis = PCABasis(n_components=4).fit(ensemble)
    validation = make_ensemble(model, random_states(model, 20, seed=7))
    for values, truth in zip(validation.normal_displacement, validation.commanded, strict=True):
        estimate = estimate_pca(basis, field_of(skin, values))
        np.testing.assert_allclose(estimate.values, truth, atol=1e-9)
        assert estimate.within_model


def test_unsupported_components_are_cut_and_said(linear):
    """Asking 10 components of a rank-4 ensemble must not turn round-off into huge parameter states."""
    skin, model, ensemble = linear
    basis = PCABasis(n_components=10).fit(ensemble)
    assert basis.n_components_ == 4
    assert any("supports only 4" in note for note in basis.notes_)
    assert np.abs(basis.component_states_).max() < 1e3
    truth = np.array([0.4, -0.9, 0.2, 0.7])
    values = model.w0 + model.R @ truth
    np.testing.assert_allclose(estimate_pca(basis, field_of(skin, values)).values, truth, atol=1e-9)


def test_explained_variance_matches_sklearn_and_selects_components(linear):
    _, _, ensemble = linear
    basis = PCABasis(n_components=None, explained_variance=0.95).fit(ensemble)
    reference = PCA().fit(ensemble.normal_displacement).explained_variance_ratio_
    np.testing.assert_allclose(basis.explained_variance_ratio_[:4], reference[:4], rtol=1e-9)
    expected = int(np.argmax(np.cumsum(reference) >= 0.95)) + 1
    assert basis.n_components_ == expected


def test_3d_components_follow_the_same_combination(linear):
    """The synthetic 3D fields have normal part = the normal field: so must every 3D component."""
    skin, _, ensemble = linear
    basis = PCABasis(n_components=4).fit(ensemble)
    normal_part = np.einsum("knj,nj->kn", basis.components_3d_, skin.normals)
    np.testing.assert_allclose(normal_part, basis.components_, atol=1e-10)
    np.testing.assert_allclose(np.sum(basis.mean_field_3d_ * skin.normals, axis=1), basis.mean_field_, atol=1e-12)


def test_bad_ensembles_are_refused(linear):
    _, _, ensemble = linear
    from dataclasses import replace

    with pytest.raises(BasisError, match="at least 3"):
        PCABasis().fit(replace(ensemble, normal_displacement=ensemble.normal_displacement[:2],
                               commanded=ensemble.commanded[:2]))
    bad = ensemble.normal_displacement.copy()
    bad[3, 5] = np.nan
    with pytest.raises(BasisError, match="NaN"):
        PCABasis().fit(replace(ensemble, normal_displacement=bad))
    with pytest.raises(BasisError, match="n_components"):
        PCABasis(n_components=0).fit(ensemble)
