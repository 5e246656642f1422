"""From an estimated parameter state to the correction the fixture adjustment robot may apply.

The correction brings every boundary back to nominal (the negated estimate). It is marked unsafe, with every reason
named, when acting on it could make things worse: too little of the part was seen, the one within-model test says the
model does not explain the part, an estimate lies outside its declared range, or an uncertainty (the full error
model's, :mod:`hood_decomp.core.method.estimation`, with the model's own physical factors considered,
:mod:`hood_decomp.core.method.model_spread`) is too large to act on. Which boundaries may still be applied is
stated per boundary. A lifted unilateral boundary (a buffer that lost contact) has no observable commanded position:
it gets no correction, and the reason says so. A measured effect (a parameter without a boundary,
:attr:`ParameterEstimate.measured_effect`) is never corrected: there is nothing to move, only an amplitude to report.
A per-cycle maximum step caps each move (:func:`limit_steps`, the rest left for the next cycle), and the next
inspection of the part tells whether the move happened (:func:`verify_move`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hood_decomp.core.types import BoundaryCorrection, MoveVerification, ParameterEstimate


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
    is in range, its total uncertainty sqrt(std^2 + model_std^2) below ``max_std_mm`` (model_std: what the model's
    physical factors, not calibrated to the part, leave open, :mod:`~hood_decomp.core.method.model_spread`; the
    reason then names the dominant factor and its one-sigma effect, also beside a measurement std above the limit
    when model_std alone exceeds it) and it is not lifted.
    When the model does not explain the field the
    reason says that the model differs from the part and names no boundary: a missing effect or other physics moves
    every estimate, so an estimate outside its range, a large uncertainty or a lifted flag is then no finding about
    that boundary (naming it would send the engineer there) and is not listed; coverage still is.
    """
    values, std = np.asarray(estimate.values, float), np.asarray(estimate.std, float)
    lifted = np.asarray(estimate.lifted, bool)
    effect = ~estimate.boundary
    # the model's physical factors the field cannot tell (model_spread): one-sigma effects (F, P) mm
    effects = estimate.model_effects
    model_std = np.zeros(len(values)) if effects is None else estimate.model_std
    problems: list[str] = []
    if not estimate.coverage >= policy.min_coverage:
        problems.append(f"coverage {estimate.coverage:.2f} below minimum {policy.min_coverage:.2f}")
    if not estimate.within_model:
        test = "" if estimate.check is None else (f" (within-model test p = {estimate.check.p_value:.2g} < "
                                                   f"{estimate.check.alpha:g})")
        problems.append(f"the model does not explain this part{test}: it lacks an effect or differs from the part, "
                        "so no boundary can be named and no estimate trusted")
    trusted = not problems
    explained = bool(estimate.within_model)
    applicable = np.zeros(len(estimate.names), dtype=bool)
    for i, (name, value, sigma, low, high, is_lifted, is_effect) in enumerate(zip(
            estimate.names, values, std, estimate.lower, estimate.upper, lifted, effect, strict=True)):
        if is_lifted:
            continue
        in_range = low - policy.range_tolerance_mm <= value <= high + policy.range_tolerance_mm
        if not in_range and explained:  # a measured effect beyond its learned range is extrapolation too
            problems.append(f"{name} = {value:.3f} mm outside its range [{low:g}, {high:g}] mm")
        if is_effect:  # nothing to move: its uncertainty gates no move
            continue
        total = float(np.hypot(sigma, model_std[i]))
        if not sigma <= policy.max_std_mm and explained:
            problems.append(f"{name} uncertainty {sigma:.3f} mm above {policy.max_std_mm:g} mm")
        # said also beside a large measurement std when the factors alone exceed the limit: a better scan would not
        # open the gate for that boundary, calibrating the model is the step (on uncalibrated bases the buffers'
        # factor std, 0.06 mm, was hidden behind their scan std)
        if explained and (model_std[i] > policy.max_std_mm or (sigma <= policy.max_std_mm < total)):
            dominant = int(np.argmax(np.abs(effects[:, i])))
            problems.append(f"model not calibrated to the part: {name} correction depends on "
                            f"{estimate.model_factors[dominant]} by +-{abs(effects[dominant, i]):.3f} mm")
        applicable[i] = trusted and in_range and total <= policy.max_std_mm
    notes = [f"{name} lifted: commanded position not observable, not corrected"
             for name, is_lifted in zip(estimate.names, lifted, strict=True) if is_lifted and explained]
    notes += [f"{name} is a measured effect: no boundary to move" for name in np.asarray(estimate.names)[effect]]
    still = lifted | effect
    return BoundaryCorrection(
        model_id=estimate.model_id,
        names=tuple(estimate.names),
        corrections=np.where(still, 0.0, -values),
        safe_to_apply=not problems,
        reason="; ".join(problems + notes),
        std=np.where(still, 0.0, std),
        applicable=applicable,
        measured_effect=None if estimate.measured_effect is None else effect,
    )


def limit_steps(correction: BoundaryCorrection, max_step_mm: np.ndarray) -> BoundaryCorrection:
    """Cap each boundary's move to its per-cycle maximum step; the rest is left for the next cycle, and said so.

    max_step_mm: (P,) mm, the largest move per cycle of each boundary of ``correction`` (0 or inf: no limit).
    Returns the correction with the capped moves, ``remaining`` (P,) mm (correction minus capped move; the next
    inspection estimates the rest afresh) and one note per capped boundary appended to ``reason``.
    """
    limit = np.asarray(max_step_mm, dtype=float)
    if limit.shape != correction.corrections.shape or np.any(limit < 0):
        raise ValueError(f"max_step_mm: expected {correction.corrections.shape} non-negative values, got {limit}")
    limit = np.where(limit > 0, limit, np.inf)
    capped = np.clip(correction.corrections, -limit, limit)
    left = correction.corrections - capped
    notes = [f"{name}: step limited to {move:+.3f} mm of {whole:+.3f} mm, {rest:+.3f} mm left for the next cycle"
             for name, move, whole, rest in zip(correction.names, capped, correction.corrections, left, strict=True)
             if rest != 0.0]
    return replace(correction, corrections=capped, remaining=left,
                   reason="; ".join(part for part in (correction.reason, *notes) if part))


def verify_move(before: ParameterEstimate, sent: BoundaryCorrection, after: ParameterEstimate,
                sigmas: float = 3.0, min_tolerance_mm: float = 0.005) -> MoveVerification:
    """Whether the correction ``sent`` after the estimate ``before`` happened, judged from the estimate ``after`` of
    the next inspection of the same part.

    A boundary was commanded when its correction was applicable and non-zero (the robot applies those). Measured
    change = after - before; its std combines both estimates' stds (independent scans). With the tolerance
    t = max(sigmas * std, min_tolerance_mm) (the std of a noise-free field is 0; the robot's repeatability is not):
    ACHIEVED when |measured - predicted| <= t; FAILED when no move was measured (|measured| <= t) or it went the
    wrong way; PARTIAL otherwise (it moved, short of or past the prediction: slipped). The summary names every
    FAILED and PARTIAL boundary with the fraction achieved.
    """
    if before.names != after.names or sent.names != before.names:
        raise ValueError(f"verify_move: boundaries differ: {before.names}, {sent.names}, {after.names}")
    applicable = np.ones(len(sent.names), bool) if sent.applicable is None else np.asarray(sent.applicable, bool)
    predicted = np.where(applicable, sent.corrections, 0.0)
    measured = after.values - before.values
    std = np.hypot(before.std, after.std)
    tolerance = np.maximum(sigmas * std, min_tolerance_mm)
    commanded = predicted != 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(commanded, measured / np.where(commanded, predicted, 1.0), np.nan)
    moved_right_way = (np.abs(measured) > tolerance) & (np.sign(measured) == np.sign(predicted))
    outcome = np.select(
        [~commanded, np.abs(measured - predicted) <= tolerance, moved_right_way],
        [MoveVerification.NOT_COMMANDED, MoveVerification.ACHIEVED, MoveVerification.PARTIAL],
        MoveVerification.FAILED)
    named = [f"{name}: {100 * share + 0.0:.0f} % of {move:+.3f} mm ({MoveVerification.OUTCOMES[code]})"
             for name, share, move, code in zip(sent.names, fraction, predicted, outcome, strict=True)
             if code in (MoveVerification.PARTIAL, MoveVerification.FAILED)]
    return MoveVerification(model_id=after.model_id, names=tuple(sent.names), predicted=predicted,
                            measured=measured, std=std, fraction=fraction, outcome=outcome.astype(np.uint8),
                            tolerance=tolerance, summary="; ".join(named))
