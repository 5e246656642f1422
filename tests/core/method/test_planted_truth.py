"""The method against truths planted by construction in toy models (tests/toy_models.py), chosen so that a broken
method cannot meet them: non-zero-mean states (eq. 5's centring), effects whose inverse partner is independent
(eq. 6's pair sum), an interaction whose basis field is known exactly, and an effect that step 5 must drop at its
default thresholds. Each test says which fault it catches; benchmarks/fault_injection.py applies those faults.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hood_decomp.core.method.decomposition import (
    DEFAULT_MAX_REMOVED_RMS_MM,
    DEFAULT_MIN_SHARE,
    decompose,
)
from hood_decomp.core.method.estimation import estimate_pca
from hood_decomp.core.method.hierarchical import HierarchicalBasis
from hood_decomp.core.method.pca import PCABasis
from tests.toy_models import field_of, full_factorial, make_ensemble, make_reduced_model, make_skin, smooth_fields


@pytest.fixture(scope="module")
def skin():
    return make_skin()


def _orthogonal_to(field: np.ndarray, span: np.ndarray) -> np.ndarray:
    """``field`` (N,) minus its least-squares projection on the rows of ``span`` (K, N)."""
    coeff = np.linalg.lstsq(span.T, field, rcond=None)[0]
    return field - coeff @ span


def test_pca_estimate_keeps_the_centring_of_eq5(skin):
    """Fails if eq. 5 drops the mean state (values = c @ states instead of mean_state + c @ states).

    The ensemble is sampled on {-0.5, 0, 1}: its mean state is not zero (the paper's and the hood's factorial plans
    are symmetric, which hides the fault). The model is linear, so every state in between is recovered exactly."""
    model = make_reduced_model(skin, seed=5, n_pads=0)
    states, rank = full_factorial(4, low=-0.5, high=1.0)
    basis = PCABasis(n_components=4).fit(make_ensemble(model, states, rank))
    assert np.abs(basis.mean_state_).min() > 0.1  # the precondition: a centring term that matters
    truth = np.random.default_rng(8).uniform(-0.5, 1.0, (12, 4))
    for state in truth:
        estimate = estimate_pca(basis, field_of(skin, model.w0 + model.R @ state))
        np.testing.assert_allclose(estimate.values, state, atol=1e-9)


def _quadratic_model(skin):
    """Linear model plus a planted field Q * LOCK_L^2: LOCK_L's lift and press fields (Q + R, Q - R) are
    independent, as a buffer's are on the hood, so LOCK_L's effect needs both fields of its pair."""
    model = make_reduced_model(skin, seed=6, n_pads=0)
    rng = np.random.default_rng(60)
    q = smooth_fields(skin.points, 1, rng, 0.6)[0]
    q3 = q[:, None] * skin.normals + 0.2 * smooth_fields(skin.points, 3, rng, 1.0).T
    states, rank = full_factorial(4)
    ensemble = make_ensemble(model, states, rank, interactions=(((2, 2), q, q3),))
    return model, q, q3, HierarchicalBasis(epsilon=1e-6).fit(ensemble)


def test_eq6_sums_the_effect_with_its_independent_inverse_partner(skin):
    """Fails if eq. 6 drops the inverse partner (d_i = |c_i B_i| instead of |c_i B_i + c_i^-1 B_i^-1|).

    Planted: LOCK_L = 0.6 gives the 3D field 0.6 R + 0.36 Q; HINGE_X = -0.4 gives -0.4 R. The fitted pair
    coefficients of LOCK_L are (0.48, -0.12): neither field alone is the effect."""
    model, q, q3, basis = _quadratic_model(skin)
    by_field = {name: basis.effect_fields_[i] for i, name in enumerate(basis.effect_names_)}
    assert set(basis.effect_names_) == {"LOADS", "HINGE_X", "HINGE_Y", "LOCK_L", "LOCK_R"}
    assert basis.independent_[by_field["LOCK_L"]].all()  # the precondition: both fields of the pair count
    state = np.array([-0.4, 0.0, 0.6, 0.0])
    values = model.w0 + model.R @ state + 0.36 * q
    result = decompose(basis, field_of(skin, values), min_share=0.0)
    effects = {e.name: e for e in result.effects}
    np.testing.assert_allclose(effects["LOCK_L"].partial_displacement,
                               np.linalg.norm(0.6 * model.R_3d[:, :, 2] + 0.36 * q3, axis=1), atol=1e-9)
    np.testing.assert_allclose(effects["HINGE_X"].partial_displacement,
                               np.linalg.norm(-0.4 * model.R_3d[:, :, 0], axis=1), atol=1e-9)
    assert result.reconstruction_rms < 1e-9


def test_interaction_partial_displacement_is_the_planted_one(skin):
    """Fails if an interaction effect's basis field, its coefficient or its 3D field is wrong (a contributions-sum-
    to-one check passes for any coefficients; this one does not).

    Planted: T * LOCK_L * LOCK_R with T orthogonal to the loads and every single-parameter field, so the greedy build
    must find exactly T as the effect ``LOCK_L & LOCK_R`` and a field at (0.3, -0.2, 0.7, 0.5) carries 0.35 T."""
    model = make_reduced_model(skin, seed=7, n_pads=0)
    rng = np.random.default_rng(70)
    t = _orthogonal_to(smooth_fields(skin.points, 1, rng, 0.5)[0], np.vstack([model.w0, model.R.T]))
    t3 = t[:, None] * skin.normals + 0.1 * smooth_fields(skin.points, 3, rng, 1.0).T
    states, rank = full_factorial(4)
    basis = HierarchicalBasis(epsilon=0.01).fit(make_ensemble(model, states, rank, interactions=(((2, 3), t, t3),)))
    assert "LOCK_L & LOCK_R" in basis.effect_names_
    state = np.array([0.3, -0.2, 0.7, 0.5])
    values = model.w0 + model.R @ state + 0.35 * t
    effects = {e.name: e for e in decompose(basis, field_of(skin, values), min_share=0.0).effects}
    np.testing.assert_allclose(effects["LOCK_L & LOCK_R"].partial_displacement,
                               np.linalg.norm(0.35 * t3, axis=1), atol=1e-9)
    for index, name in enumerate(("HINGE_X", "HINGE_Y", "LOCK_L", "LOCK_R")):
        np.testing.assert_allclose(effects[name].partial_displacement,
                                   np.linalg.norm(state[index] * model.R_3d[:, :, index], axis=1), atol=1e-9)


@pytest.fixture(scope="module")
def faint_lock(skin):
    """A linear model whose LOCK_R field is 100 times fainter than the others, and its hierarchical basis."""
    model = make_reduced_model(skin, seed=9, n_pads=0)
    scale = np.array([1.0, 1.0, 1.0, 0.01])
    model = dataclasses.replace(model, R=model.R * scale, R_3d=model.R_3d * scale)
    states, rank = full_factorial(4)
    return model, HierarchicalBasis(epsilon=0.01).fit(make_ensemble(model, states, rank))


def _normal_rms(model, index: int, value: float) -> float:
    return float(np.sqrt(np.mean((value * model.R[:, index]) ** 2)))


def test_step5_drops_a_negligible_effect_at_its_default_thresholds(skin, faint_lock):
    """Fails if step 5 (coarsening) never removes an effect at its defaults (min_share 2 %, 0.002 mm RMS)."""
    model, basis = faint_lock
    state = np.array([0.8, -0.6, 0.5, 0.1])
    assert _normal_rms(model, 3, 0.1) < DEFAULT_MAX_REMOVED_RMS_MM  # the precondition: LOCK_R is negligible
    values = model.w0 + model.R @ state
    kept = {e.name for e in decompose(basis, field_of(skin, values)).effects}
    assert kept == {"LOADS", "HINGE_X", "HINGE_Y", "LOCK_L"}
    everything = {e.name for e in decompose(basis, field_of(skin, values), min_share=0.0).effects}
    assert "LOCK_R" in everything


def test_step5_keeps_a_small_share_that_a_scan_resolves(skin, faint_lock):
    """Fails if step 5 removes an effect by share alone: LOCK_R = 1 has under 2 % of the share but a partial field
    above 0.002 mm RMS, and removing it would cost reconstruction quality a scan can see."""
    model, basis = faint_lock
    state = np.array([0.8, -0.6, 0.5, 1.0])
    assert _normal_rms(model, 3, 1.0) > DEFAULT_MAX_REMOVED_RMS_MM
    result = decompose(basis, field_of(skin, model.w0 + model.R @ state))
    shares = {e.name: e.share for e in result.effects}
    assert "LOCK_R" in shares and shares["LOCK_R"] < DEFAULT_MIN_SHARE
    assert result.reconstruction_rms < 1e-9
