"""What the model's own physical factors make uncertain in an estimate (consider parameters, Schmidt-Kalman style).

The bases are one FE model; a real part's physics differs from it (Young's modulus, pad stiffness, pad preload, ...).
A softer pad looks in one field exactly like a pad moved by its compression times the stiffness change: the field is
explained, the within-model test cannot alarm, and the measurement std says nothing about it. Such factors are not
estimated; they are *considered*: each factor's one-sigma change is applied to the reduced model at the estimated
state and contact state, the change of the skin field it makes is taken through the estimator's own linear map into
the parameters, and the result is the factor's one-sigma effect (P,) mm on the reported values. Their sum of outer
products is the model covariance (``ParameterEstimate.model_covariance``); the safety gate
(:func:`~hood_decomp.core.method.correction.plan_correction`) acts on sqrt(std^2 + model_std^2) and names the dominant
factor per boundary.

Spreads (:func:`factor_spread`): uncalibrated bases take the issue-15 ranges as *uniform half-widths* (the physics a
plant's parts scatter over, the way harness (ii) draws them; a uniform of half-width h has std h / sqrt(3)):
compliance 1/E 3 %, pad stiffness 30 % (one factor for all pads, as a family shares it), pad preload 50 % of the
model's. Calibrated bases (``hood-decomp calibrate``) take the fitted factors' std from the calibration record
(compliance log-std, per pad stiffness log-std, per pad preload in mm). Not considered (the reduced model carries no
response to them): sheet thickness (needs responses at another thickness) and gas-spring force (needs the gas
springs' response apart from gravity); benchmarks/RESULTS.md gives what that leaves open.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hood_decomp.core.types import ReducedModel

#: issue 15's ranges of the uncalibrated model's factors, relative uniform half-widths (preload: of the model's)
HALF_WIDTH = {"compliance": 0.03, "pad_stiffness": 0.30, "preload": 0.50}


@dataclass(frozen=True)
class Factor:
    """One considered factor's one-sigma change of the reduced model: compliance (relative, on every force response:
    w0, z0, G, H), pad stiffness (S,) relative, preload (S,) mm."""

    name: str
    compliance: float = 0.0
    stiffness: np.ndarray | None = None
    preload: np.ndarray | None = None


def factor_spread(model: ReducedModel, calibration: str = "") -> tuple[Factor, ...]:
    """The considered factors of ``model`` with their one-sigma changes: from the calibration record (JSON text,
    ``Bases.calibration``; its ``factor_std``) when there is one, else the uncalibrated prior :data:`HALF_WIDTH`."""
    pads = model.names[model.n_bilateral:]
    n_springs = model.k.size
    record = json.loads(calibration).get("factor_std", {}) if calibration else None
    if record is None:
        uniform = 1.0 / np.sqrt(3.0)
        return (Factor("compliance (Young's modulus)", compliance=HALF_WIDTH["compliance"] * uniform),
                Factor("pad stiffness", stiffness=np.full(n_springs, HALF_WIDTH["pad_stiffness"] * uniform)),
                Factor("pad preload", preload=HALF_WIDTH["preload"] * uniform * np.abs(model.preload)))
    factors = [Factor("calibrated compliance", compliance=float(record.get("compliance", 0.0)))]
    for p, pad in enumerate(pads):
        springs = (model.pad_of == p).astype(float)
        factors.append(Factor(f"calibrated pad stiffness of {pad}",
                              stiffness=springs * float(record.get(f"pad_stiffness:{pad}", 0.0))))
        factors.append(Factor(f"calibrated pad preload of {pad}",
                              preload=springs * float(record.get(f"preload:{pad}", 0.0))))
    return tuple(f for f in factors if f.compliance or any(np.any(v) for v in (f.stiffness, f.preload)
                                                           if v is not None))


def _forces(model: ReducedModel, active: np.ndarray, pads: np.ndarray, theta: np.ndarray, factor: Factor | None,
            sign: float) -> tuple[float, np.ndarray]:
    """(c, f): the compliance scale and the pad spring forces (S,) N of the model changed by ``sign`` times
    ``factor`` at theta = (a, b of the touching ``pads``) with the springs ``active`` in contact (the estimate's
    contact state); its skin field is c w0 + R a + c G f."""
    n_b = model.n_bilateral
    c = 1.0 + sign * (factor.compliance if factor else 0.0)
    k = model.k * (1.0 + sign * factor.stiffness) if factor is not None and factor.stiffness is not None else model.k
    preload = model.preload + sign * factor.preload if factor is not None and factor.preload is not None \
        else model.preload
    a = theta[:n_b]
    f = np.zeros(model.k.size)
    idx = np.flatnonzero(active)
    if idx.size:
        b = np.zeros(int(model.pad_of.max()) + 1)
        b[pads] = theta[n_b:]
        compliance = np.diag(1.0 / k[idx]) + c * model.H[np.ix_(idx, idx)]
        f[idx] = np.linalg.solve(compliance, b[model.pad_of[idx]] + preload[idx] - c * model.z0[idx]
                                 - model.Sa[idx] @ a)
    return c, f


def factor_effects(model: ReducedModel, factors: tuple[Factor, ...], active: np.ndarray, theta: np.ndarray,
                   to_theta: Callable[[float, np.ndarray], np.ndarray],
                   report: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(F, P) mm: each factor's one-sigma effect on the reported values.

    active: (S,) bool the estimate's contact state; theta: (n_theta,) its unknowns; to_theta(dc, df): the
    estimator's linear map (over the seen nodes) from the field change dc w0 + G df (dc: scale of the load field,
    df: (S,) pad force change, N) to theta; report: theta -> (P,) reported values. A factor's change is applied with
    both signs; the larger shift of the two (by its largest entry) is kept, signed as the + change's, so a nonlinear
    factor (the pad compliance 1/k) is not understated.
    """
    pads = np.unique(model.pad_of[active])
    _, nominal = _forces(model, active, pads, theta, None, 0.0)
    base = report(theta)
    effects = np.zeros((len(factors), base.size))
    for i, factor in enumerate(factors):
        shifts = []
        for sign in (1.0, -1.0):
            c, f = _forces(model, active, pads, theta, factor, sign)
            shifts.append(np.nan_to_num(report(theta + to_theta(c - 1.0, c * f - nominal)) - base))
        up, down = shifts
        effects[i] = up if np.max(np.abs(up)) >= np.max(np.abs(down)) else -down
    return effects
