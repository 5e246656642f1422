"""The paper's estimator (eqs. 4-5): field checks, missing nodes, noise, within_model."""

from dataclasses import replace

import numpy as np
import pytest

from hood_decomp.core.method.estimation import estimate_pca
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.method.residual import ResidualTest
from hood_decomp.errors import FieldError, ModelIdMismatchError
from tests.toy_models import field_of, full_factorial, make_ensemble, make_reduced_model, make_skin, random_states

NOISE_MM = 0.02


@pytest.fixture(scope="module")
def setup():
    skin = make_skin(30, 20)
    model = make_reduced_model(skin, seed=2, n_pads=0)
    states, rank = full_factorial(4)
    basis = PCABasis(n_components=10).fit(make_ensemble(model, states, rank))
    return skin, model, basis


def test_bad_fields_raise_clear_errors(setup):
    skin, model, basis = setup
    good = model.w0.copy()
    with pytest.raises(FieldError, match=r"expected \(600,\)"):
        estimate_pca(basis, field_of(skin, good[:-1]))
    with pytest.raises(ModelIdMismatchError, match="does not match"):
        estimate_pca(basis, replace(field_of(skin, good), model_id="0123456789abcdef"))
    with pytest.raises(FieldError, match="all NaN"):
        estimate_pca(basis, field_of(skin, np.full_like(good, np.nan)))
    sparse = np.full_like(good, np.nan)
    sparse[:60] = good[:60]
    with pytest.raises(FieldError, match=r"coverage 0\.100 is below the minimum 0\.200"):
        estimate_pca(basis, field_of(skin, sparse))
    bad = good.copy()
    bad[7] = np.inf
    with pytest.raises(FieldError, match="inf"):
        estimate_pca(basis, field_of(skin, bad))


def test_missing_nodes_keep_the_estimate_within_its_std(setup):
    """Noisy fields with a third of the skin unseen: every parameter within 4 std of the truth."""
    skin, model, basis = setup
    rng = np.random.default_rng(11)
    unseen = skin.points[:, 0] > 1000.0  # one end of the skin, ~ a third
    z_scores = []
    for truth in random_states(model, 30, seed=5):
        values = model.w0 + model.R @ truth + rng.normal(0.0, NOISE_MM, skin.n_nodes)
        values[unseen] = np.nan
        estimate = estimate_pca(basis, field_of(skin, values, NOISE_MM))
        assert estimate.coverage == pytest.approx(1 - unseen.mean())
        assert np.all(np.isnan(estimate.residual[unseen]))
        z_scores.append((estimate.values - truth) / estimate.std)
    z_scores = np.abs(np.array(z_scores))
    assert z_scores.max() < 4.0
    assert 0.3 < np.median(z_scores) < 1.2  # the std is neither wildly small nor wildly large


def test_residual_statistics_and_within_model(setup):
    skin, model, basis = setup
    rng = np.random.default_rng(3)
    truth = np.array([0.2, -0.5, 0.8, 0.1])
    noise = rng.normal(0.0, NOISE_MM, skin.n_nodes)
    estimate = estimate_pca(basis, field_of(skin, model.w0 + model.R @ truth + noise, NOISE_MM))
    assert estimate.residual_rms == pytest.approx(NOISE_MM, rel=0.15)
    assert estimate.residual_max == pytest.approx(np.nanmax(np.abs(estimate.residual)))
    assert estimate.within_model
    # An effect the model lacks: a 0.3 mm bump the basis cannot produce.
    bump = 0.3 * np.exp(-np.sum((skin.points[:, :2] - [700.0, 500.0]) ** 2, axis=1) / 150.0**2)
    test = ResidualTest().fit(skin)  # the one within-model test needs the skin's smooth modes
    assert estimate_pca(basis, field_of(skin, model.w0 + model.R @ truth + noise, NOISE_MM), test=test).within_model
    lacking = estimate_pca(basis, field_of(skin, model.w0 + model.R @ truth + noise + bump, NOISE_MM), test=test)
    assert not lacking.within_model
    assert lacking.method == "pca"
