"""From an estimated parameter state to the correction the fixture adjustment robot may apply.

The correction brings every boundary back to nominal (the negated estimate). It is marked unsafe, with every reason
named, when acting on it could make things worse: too little of the part was seen, the residual says the model lacks
an effect, an estimate lies outside its declared range, or an uncertainty is too large to act on. A lifted unilateral
boundary (a buffer that lost contact) has no observable commanded position: it gets no correction, and the reason
says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hood_decomp.core.types import BoundaryCorrection, ParameterEstimate


@dataclass(frozen=True)
class CorrectionPolicy:
    """Thresholds of :func:`plan_correction`.

    min_coverage: smallest fraction of seen skin nodes to act on, 0..1.
    max_std_mm: largest one-sigma uncertainty of any corrected parameter to act on, mm.
    range_tolerance_mm: how far an estimate may lie outside its declared range before it counts as outside, mm.
    """

    min_coverage: float = 0.6
    max_std_mm: float = 0.05
    range_tolerance_mm: float = 0.02


def plan_correction(estimate: ParameterEstimate, policy: CorrectionPolicy = CorrectionPolicy()) -> BoundaryCorrection:
    """The move (mm, one per parameter of ``estimate``) that brings each boundary to nominal, and whether it is safe.

    Every failed condition is listed in ``reason`` ("; "-separated); notes on lifted boundaries are appended.
    """
    values, std = np.asarray(estimate.values, float), np.asarray(estimate.std, float)
    lifted = np.asarray(estimate.lifted, bool)
    problems: list[str] = []
    if not estimate.coverage >= policy.min_coverage:
        problems.append(f"coverage {estimate.coverage:.2f} below minimum {policy.min_coverage:.2f}")
    if not estimate.within_model:
        problems.append(f"residual {estimate.residual_rms:.3f} mm RMS is more than the scan noise explains: "
                        "the model lacks an effect")
    for name, value, low, high, is_lifted in zip(estimate.names, values, estimate.lower, estimate.upper, lifted,
                                                 strict=True):
        if not is_lifted and not (low - policy.range_tolerance_mm <= value <= high + policy.range_tolerance_mm):
            problems.append(f"{name} = {value:.3f} mm outside its range [{low:g}, {high:g}] mm")
    for name, sigma, is_lifted in zip(estimate.names, std, lifted, strict=True):
        if not is_lifted and not sigma <= policy.max_std_mm:
            problems.append(f"{name} uncertainty {sigma:.3f} mm above {policy.max_std_mm:g} mm")
    notes = [f"{name} lifted: commanded position not observable, not corrected"
             for name, is_lifted in zip(estimate.names, lifted, strict=True) if is_lifted]
    corrections = np.where(lifted, 0.0, -values)
    return BoundaryCorrection(
        model_id=estimate.model_id,
        names=tuple(estimate.names),
        corrections=corrections,
        safe_to_apply=not problems,
        reason="; ".join(problems + notes),
    )
