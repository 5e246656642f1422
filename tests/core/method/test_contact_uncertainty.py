"""The contact-aware estimator's stated std on noise-only fields of the coarse hood (issue 15).

Truth: random states in the declared ranges solved by the reduced FE model with its exact pad contact (the estimator
fits the same model but must find the contact state from the noisy field: a different path); white node noise
0.01-0.05 mm, stated as the field's error model.
"""

from __future__ import annotations

import numpy as np

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.method.bases import estimate_field
from hood_decomp.core.types import DisplacementField, FieldErrorModel

Z95 = 1.959964


def test_lock_and_buffer_stds_cover_the_contact_state_ambiguity(coarse_hood):
    """Fails if the spread between the contact states a noisy field supports is left out of the stated covariance
    (locks and buffers then hold 91-92 % inside their 95 % interval: 91.6 % pooled over 2,000 fields on 2026-11-24)
    or if it is overstated (above 97 %). Pooled over locks and buffers whose contact flag is right, 600 fields: the
    binomial std of the pooled fraction is ~0.5 %; with the term it was 94.8 % on 2,000 fields."""
    bases, reduced, skin = coarse_hood.bases, coarse_hood.reduced, coarse_hood.skin
    lower, upper = bases.pca.lower_, bases.pca.upper_
    n_b = reduced.n_bilateral
    rng = np.random.default_rng(7)
    states = rng.uniform(lower, upper, size=(600, lower.size))
    members = solve_members(reduced, states)
    inside = []
    for k in range(states.shape[0]):
        sigma = rng.uniform(0.01, 0.05)
        values = members.normal_displacement[k] + rng.normal(0.0, sigma, skin.n_nodes)
        field = DisplacementField(skin.model_id, values, 1.0, float("nan"), FieldErrorModel.stated(sigma, skin.n_nodes))
        estimate = estimate_field(bases, field)
        true_lifted = members.contact_fraction[k] == 0.0
        z = (estimate.values - members.effective[k]) / estimate.std
        right = np.concatenate([np.ones(n_b, bool), estimate.lifted[n_b:] == true_lifted])
        locks_and_buffers = np.arange(z.size) >= n_b - 2
        inside.extend(np.abs(z[right & locks_and_buffers]) <= Z95)
    fraction = float(np.mean(inside))
    assert 0.93 <= fraction <= 0.97, f"{fraction:.3f} of lock and buffer errors inside the stated 95 % interval"


def test_a_field_the_model_misfits_gets_finite_std_set_by_its_residual(coarse_hood):
    """Fails if the contact states' Akaike weights are taken at the stated noise where the model misfits: a 0.3 mm
    bump the model lacks, with 0.0005 mm stated noise, puts the reported state 2,150 units above another (the weight
    exp(+1075) overflowed and the estimate was refused with a LinAlgError, as on a calibrated default-hood scan), or
    if the spread then depends on the stated noise rather than on what the residual supports (0.0005 against 0.002 mm:
    the same misfit, the same std within 10 %)."""
    bases, reduced, skin = coarse_hood.bases, coarse_hood.reduced, coarse_hood.skin
    points = np.asarray(skin.points)
    rng = np.random.default_rng(3)
    for _ in range(3):  # the third draw of this seed is a part whose contact states the old weights overflowed on
        state = rng.uniform(bases.pca.lower_, bases.pca.upper_)
        centre = points[rng.integers(len(points))]
        unit_noise = rng.normal(0.0, 1.0, skin.n_nodes)
    truth = solve_members(reduced, state[None]).normal_displacement[0]
    bump = 0.3 * np.exp(-np.sum((points - centre) ** 2, axis=1) / (2 * 150.0**2))
    stds = []
    for noise in (0.0005, 0.002):
        field = DisplacementField(skin.model_id, truth + bump + noise * unit_noise, 1.0, noise,
                                  FieldErrorModel.stated(noise, skin.n_nodes))
        estimate = estimate_field(bases, field)
        assert np.all(np.isfinite(estimate.std)) and not estimate.within_model
        stds.append(estimate.std)
    np.testing.assert_allclose(stds[0], stds[1], rtol=0.1)
