"""Contact-aware estimator on a hand-made ReducedModel whose truth comes from an exact (enumerated) LCP."""


import dataclasses

import numpy as np
import pytest

from hood_decomp.core.method.contact_estimation import ContactEstimator
from hood_decomp.core.method.estimation import estimate_pca
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.errors import ModelError
from tests.toy_models import field_of, full_factorial, make_ensemble, make_reduced_model, make_skin, random_states

N_BILATERAL = 4


@pytest.fixture(scope="module")
def setup():
    skin = make_skin()
    model = make_reduced_model(skin, seed=0, springs_per_pad=3)
    validation = make_ensemble(model, random_states(model, 60, seed=21))
    estimator = ContactEstimator().fit(model, np.full(6, -1.0), np.full(6, 1.0))
    return skin, model, validation, estimator


def test_noise_free_recovery_and_lifted_buffers(setup):
    skin, _, validation, estimator = setup
    lifted_seen = 0
    for i in range(validation.n_members):
        estimate = estimator.estimate(field_of(skin, validation.normal_displacement[i]))
        truth_lifted = validation.contact_fraction[i] == 0
        np.testing.assert_array_equal(estimate.lifted[N_BILATERAL:], truth_lifted)
        # Bilateral and touching pads: the commanded state; lifted pads: the part's position (effective state).
        np.testing.assert_allclose(estimate.values, validation.effective[i], atol=1e-9)
        commanded = validation.commanded[i, N_BILATERAL:]
        assert np.all(commanded[truth_lifted] <= estimate.values[N_BILATERAL:][truth_lifted] + 1e-9)
        assert estimate.residual_rms < 1e-10 and estimate.within_model and estimate.method == "contact"
        lifted_seen += int(truth_lifted.sum())
    assert lifted_seen >= 10  # the validation set really exercises lifted buffers


def test_noisy_partial_fields_stay_within_std(setup):
    skin, _, validation, estimator = setup
    rng = np.random.default_rng(4)
    unseen = skin.points[:, 1] < 250.0
    z_scores = []
    for i in range(30):
        values = validation.normal_displacement[i] + rng.normal(0.0, 0.02, skin.n_nodes)
        values[unseen] = np.nan
        estimate = estimator.estimate(field_of(skin, values, 0.02))
        touching = ~estimate.lifted
        z_scores.append(((estimate.values - validation.effective[i]) / estimate.std)[touching])
        assert np.all(np.abs(estimate.values - validation.effective[i]) < 0.1)
    assert np.abs(np.concatenate(z_scores)).max() < 5.0


def test_contact_estimator_beats_the_paper_estimator_with_buffers(setup):
    """With a pad contact nonlinearity the PCA basis is only approximate; the reduced model is exact."""
    skin, model, validation, estimator = setup
    states, rank = full_factorial(6)
    basis = PCABasis(n_components=10).fit(make_ensemble(model, states, rank))
    values = validation.normal_displacement[0]
    pca_error = np.abs(estimate_pca(basis, field_of(skin, values)).values - validation.effective[0]).max()
    contact_error = np.abs(estimator.estimate(field_of(skin, values)).values - validation.effective[0]).max()
    assert contact_error < 1e-9 < pca_error


def test_bad_ranges_are_refused(setup):
    _, model, _, _ = setup
    with pytest.raises(ModelError, match=r"shape \(6,\)"):
        ContactEstimator().fit(model, np.zeros(5), np.zeros(6))


def test_a_lifted_pads_model_std_counts_the_preload_it_is_read_from(setup):
    """Fails if a lifted pad's stated model effect leaves out that its value, the part's position z - preload, moves
    with the preload itself (a part whose preload differs from the model's has its position elsewhere, which the
    estimate made with the model's preload does not follow; the effect was 0 before), or if it is added with the wrong
    sign. Truth from another path: the part with the changed preload solved by exact pad contact (solve_members),
    estimated by the nominal estimator, minus the changed part's own position there. The touching pad and the
    bilateral values must stay unaffected (a lifted pad's preload moves no force)."""
    from dataclasses import replace

    from hood_decomp.core.fe.ensemble import solve_members
    from hood_decomp.core.method.model_spread import Factor

    skin, model, _, _ = setup
    pad0 = (model.pad_of == 0).astype(float)
    part = replace(model, preload=model.preload + 0.03 * pad0)
    factor = Factor("preload", plus=part, minus=replace(model, preload=model.preload - 0.03 * pad0))
    estimator = ContactEstimator().fit(model, np.full(6, -1.0), np.full(6, 1.0), factors=(factor,))
    rng = np.random.default_rng(8)
    for _ in range(3):
        state = np.concatenate([rng.uniform(-0.5, 0.5, N_BILATERAL), [-1.0, 0.5]])
        estimate = estimator.estimate(field_of(skin, solve_members(model, state[None]).normal_displacement[0]))
        assert estimate.lifted[N_BILATERAL] and not estimate.lifted[N_BILATERAL + 1]
        truth = solve_members(part, state[None])
        error = estimator.estimate(field_of(skin, truth.normal_displacement[0])).values - truth.effective[0]
        assert abs(error[N_BILATERAL]) > 0.02  # the preload really moves the lifted pad's error
        np.testing.assert_allclose(estimate.model_effects[0], error, atol=1e-6)


def test_the_fits_own_projection_judges_as_the_tests_own_pass(setup):
    """The PCA and contact-aware fits hand the within-model test their residual's projection on the fitted fields,
    taken from their right-hand sides (an ordinary fit: rhs less its normal matrix times its coefficients; the
    contact fit's refinement step carried). Fails if the test an estimate reports differs from the skin's test made
    afresh on that estimate's residual with its own pass over the nodes: fields with a stated white noise, holes,
    and a smooth effect the model lacks (so that the statistic is not near zero). It cannot see the refinement's
    own term (normal times the refinement's step: ~1e-10 of the statistic) nor a PCA projection handed over as 0
    (an ordinary fit's is 0 to round-off); it sees the right-hand side handed over as it is, or the contact
    fit's projection on the fields outside its contact state dropped."""
    from hood_decomp.core.method.residual import ResidualTest
    from hood_decomp.core.types import FieldErrorModel

    skin, model, validation, _ = setup
    test = ResidualTest().fit(skin)
    contact = ContactEstimator().fit(model, np.full(6, -1.0), np.full(6, 1.0), test=test)
    states, rank = full_factorial(6)
    basis = PCABasis(n_components=10).fit(make_ensemble(model, states, rank))
    rng = np.random.default_rng(9)
    lacking = 0.01 * np.sin(skin.points[:, 0] / 300.0) * np.cos(skin.points[:, 1] / 200.0)
    for i in range(4):
        values = validation.normal_displacement[i] + rng.normal(0.0, 0.02, skin.n_nodes) + (i % 2) * lacking
        values[rng.random(skin.n_nodes) < 0.15] = np.nan
        field = dataclasses.replace(field_of(skin, values), error_model=FieldErrorModel.stated(0.02, skin.n_nodes))
        for estimate, span in ((estimate_pca(basis, field, test=test), basis.components_.T),
                               (contact.estimate(field), contact.fields_.T)):
            afresh = test.check(estimate.residual, span, field.errors)
            for name in ("statistic", "noise_scale", "p_value"):
                assert getattr(estimate.check, name) == pytest.approx(getattr(afresh, name), rel=1e-9), name

