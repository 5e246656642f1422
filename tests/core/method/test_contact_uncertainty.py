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
