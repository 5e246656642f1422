"""From an estimated parameter state to the correction the fixture adjustment robot may apply.

The correction brings every boundary back to nominal (the negated estimate). It is marked unsafe, with every reason
named, when acting on it could make things worse: too little of the part was seen, the one within-model test says the
model does not explain the part, an estimate lies outside its declared range, or an uncertainty (the full error
model's, :mod:`hood_decomp.core.method.estimation`) is too large to act on. Which boundaries may still be applied is
stated per boundary. A lifted unilateral
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
    # 4.5 std of 0.0045 mm is 0.02 mm: a correction the gate lets through is then wrong by more than 0.02 mm only
    # beyond 4.5 std (issue 15: no applied correction wrong by more than 0.02 mm)
    max_std_mm: float = 0.0045
    range_tolerance_mm: float = 0.02


def plan_correction(estimate: ParameterEstimate, policy: CorrectionPolicy = CorrectionPolicy()) -> BoundaryCorrection:
    """The move (mm, one per parameter of ``estimate``) that brings each boundary to nominal, and whether it is safe.

    Every failed condition is listed in ``reason`` ("; "-separated); notes on lifted boundaries are appended.
    Per boundary, ``applicable`` says whether its own correction may be applied when the whole is not safe: only
    when the field is within the model with enough coverage (otherwise no number can be trusted), and its estimate
    is in range, its std below ``max_std_mm`` and it is not lifted. When the model does not explain the field the
    reason says that the model differs from the part and names no boundary: a missing effect moves every estimate.
    """
    values, std = np.asarray(estimate.values, float), np.asarray(estimate.std, float)
    lifted = np.asarray(estimate.lifted, bool)
    problems: list[str] = []
    if not estimate.coverage >= policy.min_coverage:
        problems.append(f"coverage {estimate.coverage:.2f} below minimum {policy.min_coverage:.2f}")
    if not estimate.within_model:
        test = "" if estimate.check is None else (f" (within-model test p = {estimate.check.p_value:.2g} < "
                                                   f"{estimate.check.alpha:g})")
        problems.append(f"the model does not explain this part{test}: it lacks an effect or differs from the part, "
                        "so no boundary can be named and no estimate trusted")
    trusted = not problems
    applicable = np.zeros(len(estimate.names), dtype=bool)
    for i, (name, value, sigma, low, high, is_lifted) in enumerate(zip(
            estimate.names, values, std, estimate.lower, estimate.upper, lifted, strict=True)):
        if is_lifted:
            continue
        in_range = low - policy.range_tolerance_mm <= value <= high + policy.range_tolerance_mm
        if not in_range:
            problems.append(f"{name} = {value:.3f} mm outside its range [{low:g}, {high:g}] mm")
        if not sigma <= policy.max_std_mm:
            problems.append(f"{name} uncertainty {sigma:.3f} mm above {policy.max_std_mm:g} mm")
        applicable[i] = trusted and in_range and sigma <= policy.max_std_mm
    notes = [f"{name} lifted: commanded position not observable, not corrected"
             for name, is_lifted in zip(estimate.names, lifted, strict=True) if is_lifted]
    corrections = np.where(lifted, 0.0, -values)
    return BoundaryCorrection(
        model_id=estimate.model_id,
        names=tuple(estimate.names),
        corrections=corrections,
        safe_to_apply=not problems,
        reason="; ".join(problems + notes),
        std=np.where(lifted, 0.0, std),
        applicable=applicable,
    )
