"""Section 4.1's validation on the built-in hood: the paper's PCA estimator and the contact-aware estimator on random
members whose truth is the embedded FE solver with its exact pad contact (an independent path from the estimators).

Shared by tests/core/method/test_method_hood.py (coarse, and a subset of members at default resolution) and
benchmarks/bench_method_hood.py (default resolution, 1400 members, the Fig. 8/9/10-style figures).
"""

from __future__ import annotations

import time

import numpy as np

from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, validation_plan
from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.core.method.contact_estimation import ContactEstimator
from hood_decomp.core.method.estimation import estimate_pca
from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.types import DisplacementField

NOISE_MM = 0.02
VALIDATION_SEED = 1


def build(resolution: str):
    """(model, skin, reduced model, the full-factorial training ensemble) of the built-in hood at ``resolution``."""
    model = build_hood(resolution)
    skin = skin_surface(model)
    reduced = reduce_model(build_solver(model))
    commanded, rank = factorial_plan(model.lower, model.upper)
    return model, skin, reduced, simulate_ensemble(reduced, commanded, rank, model.lower, model.upper)


def validation_members(model, reduced, n_validation: int, seed: int = VALIDATION_SEED):
    """``n_validation`` uniform random members (an Ensemble) solved with exact pad contact."""
    plan = validation_plan(model.lower, model.upper, n_validation, seed=seed)
    return simulate_ensemble(reduced, plan, np.full(n_validation, -1), model.lower, model.upper)


def field(skin, values, noise=float("nan")):
    return DisplacementField(skin.model_id, values, float(np.isfinite(values).mean()), noise)


def run_validation(skin, reduced, training, validation, model, noise_seed=0):
    """Errors (M, P) mm of the PCA and contact estimators, noise-free and noisy, and lifted-buffer checks."""
    pca = PCABasis(n_components=10).fit(training)
    contact = ContactEstimator().fit(reduced, model.lower, model.upper)
    rng = np.random.default_rng(noise_seed)
    n_b = reduced.n_bilateral
    out = {"pca": [], "contact": [], "contact_noisy": [], "noisy_std": [], "noisy_flag_ok": [], "observable": [],
           "lifted_wrong": 0, "commanded_above": 0.0, "seconds": []}
    for values, effective, commanded, fraction in zip(validation.normal_displacement, validation.effective,
                                                      validation.commanded, validation.contact_fraction, strict=True):
        out["pca"].append(estimate_pca(pca, field(skin, values)).values - effective)
        start = time.perf_counter()
        estimate = contact.estimate(field(skin, values))
        out["seconds"].append(time.perf_counter() - start)
        out["contact"].append(estimate.values - effective)
        lifted = fraction == 0
        out["observable"].append(np.concatenate([np.ones(n_b, bool), ~lifted]))  # hinges, locks, pads in contact
        out["lifted_wrong"] += int(np.any(estimate.lifted[n_b:] != lifted))
        above = commanded[n_b:][lifted] - estimate.values[n_b:][lifted]
        out["commanded_above"] = max(out["commanded_above"], float(above.max(initial=-np.inf)))
        noisy = values + rng.normal(0.0, NOISE_MM, values.size)
        estimate = contact.estimate(field(skin, noisy, NOISE_MM))
        out["contact_noisy"].append(estimate.values - effective)
        out["noisy_std"].append(estimate.std)
        out["noisy_flag_ok"].append(np.concatenate([np.ones(n_b, bool), estimate.lifted[n_b:] == lifted]))
    for key in ("pca", "contact", "contact_noisy", "noisy_std", "noisy_flag_ok", "observable"):
        out[key] = np.array(out[key])
    return pca, out
