"""The contact-aware estimator on parts its own model did not make: truth from a finer mesh, and from pads 15 % stiffer
(or softer) with 15 % less (or more) preload. The coarse hood's bases estimate them; the errors are what a model that
differs from the part costs today, bounded at 1.5x today's figures so that a regression shows. (Reaching the paper's
accuracy on such parts is the calibration issue's work, not this test's.)

Today's figures (2026-11-23, coarse hood 64 x 74, 40 random members, seed 5), max |error| mm per parameter
HINGE_X, HINGE_Y, LOCK_L, LOCK_R, BUFFER_R, BUFFER_L:
- finer mesh (96 x 111 skin grid, interpolated to the coarse skin): 0.134, 0.0064, 0.065, 0.039, 0.38, 0.28
  (a 127 x 147 grid gives the same within 0.03 mm: the error is the coarse model's discretisation, ~2 %);
- pads k +15 %, preload -15 %: 0.0033, 0.0001, 0.0007, 0.0013, 0.082, 0.063;
- pads k -15 %, preload +15 %: 0.0028, 0.0001, 0.0012, 0.0014, 0.104, 0.083.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import LinearNDInterpolator

from hood_decomp.core.fe.ensemble import simulate_ensemble, validation_plan
from hood_decomp.core.fe.hood_preset import PAD_PRELOAD, PAD_STIFFNESS, build_hood, half_width
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.core.method.contact_estimation import ContactEstimator
from hood_decomp.core.types import DisplacementField

N_MEMBERS = 40


def _grid_coordinates(points: np.ndarray) -> np.ndarray:
    """(N, 2) (x, eta) of skin points (N, 3) mm: the hood's skin is a structured grid in these coordinates."""
    return np.column_stack([points[:, 0], points[:, 1] / half_width(points[:, 0])])


def _errors(coarse_hood, model, interpolate: bool) -> tuple[np.ndarray, int]:
    """|estimate - truth| (M, P) mm of the coarse hood's contact estimator on ``model``'s members, and the number of
    wrong lifted flags; ``interpolate`` maps another mesh's skin field onto the coarse skin."""
    skin = skin_surface(model)
    reduced = reduce_model(build_solver(model))
    plan = validation_plan(model.lower, model.upper, N_MEMBERS, seed=5)
    members = simulate_ensemble(reduced, plan, np.full(N_MEMBERS, -1), model.lower, model.upper)
    estimator = ContactEstimator().fit(coarse_hood.reduced, coarse_hood.model.lower, coarse_hood.model.upper)
    target = _grid_coordinates(coarse_hood.skin.points)
    n_b = reduced.n_bilateral
    errors, wrong = [], 0
    for values, effective, fraction in zip(members.normal_displacement, members.effective, members.contact_fraction,
                                           strict=True):
        if interpolate:
            values = LinearNDInterpolator(_grid_coordinates(skin.points), values)(target)
        field = DisplacementField(coarse_hood.skin.model_id, values, float(np.isfinite(values).mean()), float("nan"))
        estimate = estimator.estimate(field)
        errors.append(np.abs(estimate.values - effective))
        wrong += int(np.count_nonzero(estimate.lifted[n_b:] != (fraction == 0)))
    return np.array(errors), wrong


@pytest.mark.slow
def test_finer_mesh_truth(coarse_hood):
    """Fails if the estimates of a part solved on a finer mesh get worse than 1.5x today's (module docstring)."""
    errors, wrong = _errors(coarse_hood, build_hood("coarse", grid=(96, 111)), interpolate=True)
    today = np.array([0.134, 0.0064, 0.065, 0.039, 0.38, 0.28])
    assert np.all(errors.max(axis=0) <= 1.5 * today), errors.max(axis=0)
    assert np.all(np.median(errors, axis=0) <= 1.5 * np.array([0.052, 0.0027, 0.0059, 0.0114, 0.035, 0.027]))
    assert wrong <= 14  # today 9 of 80 pad states


@pytest.mark.parametrize(("stiffness", "preload", "today", "today_wrong"), [
    (1.15, 0.85, (0.0033, 0.0001, 0.0007, 0.0013, 0.082, 0.063), 5),
    (0.85, 1.15, (0.0028, 0.0001, 0.0012, 0.0014, 0.104, 0.083), 19),
])
def test_perturbed_pad_truth(coarse_hood, stiffness, preload, today, today_wrong):
    """Fails if the estimates of a part whose pads differ from the model (stiffness and preload +-15 %) get worse than
    1.5x today's: hinges and locks stay within micrometres, buffers within 0.16 mm."""
    model = build_hood("coarse", pad_stiffness=PAD_STIFFNESS * stiffness, pad_preload=PAD_PRELOAD * preload)
    errors, wrong = _errors(coarse_hood, model, interpolate=False)
    floor = 1e-4  # below this the figures are rounding
    assert np.all(errors.max(axis=0) <= np.maximum(1.5 * np.array(today), floor)), errors.max(axis=0)
    assert wrong <= 1.5 * today_wrong
