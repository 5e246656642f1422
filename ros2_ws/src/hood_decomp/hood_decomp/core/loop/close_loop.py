"""Closing the loop (docs/close_loop.md): locate the residual, trace it to an effect the model lacks, add that effect
as a parameter, rebuild the bases and report the error before and after.

1. **Residual** of every field against the current bases (:mod:`hood_decomp.core.method.residual`): the one
   within-model test each estimate carries (:func:`~hood_decomp.core.method.residual.check_residual`, against the
   field's error model; Bonferroni over the fields) and the regions where the residual exceeds the noise. The same
   test decides whether the fields are within the model with a candidate or a pair (step 2) and after (step 4).
2. **Trace**: every candidate effect (:mod:`hood_decomp.core.loop.candidates`) is appended to the reduced model as one
   more bilateral input and every field is estimated again with the contact-aware estimator, so the pads' contact
   state is solved anew with the candidate in place (a lifted buffer stays without effect, a seated one keeps its
   reaction). With residual sums of squares RSS0 (current model, p_i unknowns in field i) and RSS_c (with candidate
   c), each field weighted by its noise 1 / sigma_i^2 and q fields, the residual reduction is tested by

       F_c = (sum_i w_i (RSS0_i - RSS_c,i) / q) / (sum_i w_i RSS_c,i / d),   d = sum_i (n_i - p_i - 1),

   an F(q, d) statistic under "c does nothing"; its p-value is Bonferroni-adjusted over the C candidates.
   The best candidate (smallest weighted RSS) is judged by three tests: **significant** (adjusted p < alpha),
   **decisive** against the runner-up (the runner-up's extra weighted RSS, in units of the best fit's residual
   variance, exceeds the chi-square(q) quantile at alpha: a likelihood ratio between the two one-effect models) and
   how much of the residual energy beyond noise, sum_i (RSS0_i / sigma_i^2 - dof_i), it removes.
   **Pairs.** A missing effect need not be one candidate column: a hinge moved obliquely is two. When the best single
   candidate is significant, decisive and removes at least :data:`PARTIAL_MIN` of the excess but leaves the fields
   outside the model, the best single is fitted jointly with every other candidate. A pair is taken when it brings
   the fields within the model, its second effect is significant (F(q, d - q) on the RSS it removes beyond the best
   single, Bonferroni over the pairs) and it is decisive against the runner-up pair. A pair completes what a single
   already names: a discrepancy no single candidate explains is not dressed up as two; and when two pairs fit
   alike, neither is named as found.
   The outcome: a pair, or a single that removes at least :data:`PARTIAL_MIN` of the excess and brings the fields
   within the model, is **found** and added. A significant,
   decisive single that removes at least :data:`PARTIAL_MIN` of the residual energy beyond noise (the residual RMS
   beyond noise at least halved) but leaves the fields outside the model (with any pair) is **partial**: it is named
   as the nearest candidate, with its magnitude and the residual with it, but not added: the model still lacks
   something near it, and an approximate column would move the declared estimates (a hinge raised 30 mm from the
   candidate's patch: HINGE_X 0.15 -> 0.32 mm off on the coarse hood), so the declared estimates stay the ones
   before. Otherwise nothing is named: "ambiguous" (a candidate removes that much but another does almost as well) or
   "unexplained", with the residual regions showing where the model fails, rather than a boundary named for a
   discrepancy no candidate has.
3. **Augment**: the winning effect becomes a parameter with the symmetric range +-h,
   h = :data:`RANGE_MARGIN` x max_i (|estimate_i| + 3 std_i) rounded up to two significant digits; the reduced model
   gets its column (:func:`~hood_decomp.core.loop.candidates.augment_reduced`, the same column
   ``reduce_model(solver, extra=...)`` builds for a motion); the full-factorial ensemble is extended by the new
   parameter's min and max layers only, the old members being its 0 layer (:func:`extend_ensemble`); both bases are
   rebuilt (:func:`hood_decomp.core.method.bases.build_bases`) and every field is estimated again.
``max_effects`` 2 (the default) lets a pair be added, 1 only a single candidate.

Progress goes to this module's logger. The JSON report of a :class:`CloseLoopResult` is
:func:`hood_decomp.io.close_loop_report.close_loop_report`.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, solve_members
from hood_decomp.core.loop.candidates import CandidateFields, augment_reduced
from hood_decomp.core.loop.scan_skin import with_reading_bias
from hood_decomp.core.method.bases import (
    Bases,
    analyse_estimate,
    build_bases,
    estimate_field,
    fitted_unknowns,
    node_field,
    rebuilt_like,
)
from hood_decomp.core.method.contact_estimation import ContactEstimator
from hood_decomp.core.method.distributions import chi2_isf, f_sf
from hood_decomp.core.method.estimation import DEFAULT_MIN_COVERAGE
from hood_decomp.core.method.residual import (
    DEFAULT_ALPHA,
    DEFAULT_NOISE_MM,
    ResidualAnalysis,
    ResidualTest,
    noise_level,
)
from hood_decomp.core.types import DisplacementField, Ensemble, ParameterEstimate, ReducedModel
from hood_decomp.errors import BasisError, EnsembleError, FieldError, ModelError, ModelIdMismatchError

logger = logging.getLogger(__name__)

#: a candidate that leaves the fields outside the model is still added ("partial") when it removes at least this
#: fraction of the residual energy beyond noise: the residual RMS beyond noise at least halved (1 - 0.5^2)
PARTIAL_MIN = 0.75
#: the new parameter's range covers this factor times (|estimate| + 3 std)
RANGE_MARGIN = 1.5
STATUSES = ("within_model", "found", "partial", "ambiguous", "unexplained")


@dataclass(frozen=True)
class CandidateScore:
    """How well one candidate explains the residual of all fields (F of them) together with the current model.

    rss_mm2: (F,) residual sum of squares with the candidate, mm^2. weighted_rss: sum_i RSS_i / sigma_i^2.
    explained: fraction of the residual energy beyond noise the candidate removes (can be < 0 or > 1 by noise).
    f_statistic, p_value (raw), p_adjusted (Bonferroni over the candidates). values, std: (F,) the candidate's
    estimated magnitude per field in its unit (mm or N).
    """

    name: str
    kind: str
    unit: str
    description: str
    rss_mm2: np.ndarray
    weighted_rss: float
    explained: float
    f_statistic: float
    p_value: float
    p_adjusted: float
    values: np.ndarray
    std: np.ndarray


@dataclass(frozen=True)
class PairScore:
    """Two candidates fitted jointly (module docstring, step 2, "Pairs").

    names: the two candidates, the better single first. rss_mm2: (F,) RSS with both; weighted_rss: sum_i RSS_i /
    sigma_i^2; explained: fraction of the residual energy beyond noise the pair removes. f_statistic, p_adjusted
    (Bonferroni over the pairs): the second effect over the better single. within_after: the fields are within the
    model with the pair. values, std: (F, 2) the two magnitudes per field in their units.
    """

    names: tuple[str, str]
    rss_mm2: np.ndarray
    weighted_rss: float
    explained: float
    f_statistic: float
    p_adjusted: float
    within_after: bool
    values: np.ndarray
    std: np.ndarray


@dataclass(frozen=True)
class Trace:
    """Ranking of the candidates for one step (best first) and the decision (module docstring, step 2).

    rss_before_mm2: (F,) RSS of the current model; excess: residual energy beyond noise, sum_i (RSS0_i/sigma_i^2 -
    dof_i). decisiveness: the runner-up's extra weighted RSS over the best fit's residual variance (inf with one
    candidate); decisive_threshold: chi-square(F) quantile at alpha. within_after: the fields are within the model
    with the best single candidate. pairs: the jointly fitted pairs, best first (empty when a single candidate was
    enough or none was significant). outcome: "found", "partial", "ambiguous" or "unexplained"; named: the
    candidates named (one, or a pair when found; empty unless found or partial), added only when found;
    named_estimates: (F,) estimates with them.
    """

    scores: tuple[CandidateScore, ...]
    rss_before_mm2: np.ndarray
    excess: float
    significant: bool
    decisiveness: float
    decisive_threshold: float
    decisive: bool
    within_after: bool
    pairs: tuple[PairScore, ...]
    outcome: str
    named: tuple[str, ...]
    reason: str
    named_estimates: tuple[ParameterEstimate, ...]

    @property
    def best(self) -> CandidateScore:
        return self.scores[0]

    @property
    def conclusive(self) -> bool:
        """The named effects are added ("found")."""
        return self.outcome == "found"


@dataclass(frozen=True)
class AddedEffect:
    """An effect added as a parameter: name, kind, unit, boundary, description; values, std (F,) its estimates after
    the rebuild (unit mm or N); lower, upper: its declared range."""

    name: str
    kind: str
    unit: str
    boundary: str
    description: str
    values: np.ndarray
    std: np.ndarray
    lower: float
    upper: float


@dataclass(frozen=True)
class CloseLoopResult:
    """Outcome of :func:`close_loop` on F fields.

    status: "within_model" (nothing to add), "found" (effects added and the fields within the model after),
    "partial" (a candidate named that reduces the residual, but the fields stay outside the model with it: the model
    still lacks something near it; nothing added), "ambiguous" (a candidate explains it but not decisively better
    than another) or "unexplained" (no candidate explains it; nothing added). message: one readable sentence.
    before/after: (F,) estimates; analyses_*: their residual analyses (after: empty when nothing was added).
    within_model_*: combined chi-square decision over the fields. traces: the one trace (a tuple for the report).
    bases_after: the rebuilt bases (None when nothing was added). timings: seconds.
    """

    status: str
    message: str
    before: tuple[ParameterEstimate, ...]
    analyses_before: tuple[ResidualAnalysis, ...]
    within_model_before: bool
    p_value_before: float
    traces: tuple[Trace, ...]
    added: tuple[AddedEffect, ...]
    bases_after: Bases | None
    after: tuple[ParameterEstimate, ...]
    analyses_after: tuple[ResidualAnalysis, ...]
    within_model_after: bool | None
    p_value_after: float | None
    timings: dict[str, float]


# --- residual of a set of fields ---------------------------------------------------------------------------------
def _decide(estimates: Sequence[ParameterEstimate], alpha: float) -> tuple[float, bool]:
    """The decision over F fields by the one within-model test each estimate carries
    (:func:`hood_decomp.core.method.residual.check_residual`): the smallest p-value, Bonferroni-adjusted over the
    fields, against alpha. (adjusted p-value, within)."""
    p_value = min(1.0, len(estimates) * min(e.check.p_value for e in estimates))
    return p_value, p_value >= alpha


def _analyse(bases: Bases, estimates: Sequence[ParameterEstimate], noise: Sequence[float], alpha: float
             ) -> tuple[tuple[ResidualAnalysis, ...], float, bool]:
    """Residual analyses of the estimates (each with its field's test and the regions where the residual exceeds
    ``noise``) and the decision over all fields (:func:`_decide`)."""
    analyses = tuple(analyse_estimate(bases, e, sigma, alpha) for e, sigma in zip(estimates, noise, strict=True))
    return (analyses, *_decide(estimates, alpha))


def _declared_shifts(bases: Bases, before: Sequence[ParameterEstimate], named: Sequence[ParameterEstimate]) -> float:
    """Largest change (mm) of a declared parameter seen (not lifted) in both, between estimates without and with the
    named candidates."""
    shifts = [0.0]
    for old, new in zip(before, named, strict=True):
        for label in bases.pca.names_:
            i, j = old.names.index(label), new.names.index(label)
            if not (old.lifted[i] or new.lifted[j]):
                shifts.append(abs(float(new.values[j] - old.values[i])))
    return max(shifts)


# --- tracing -----------------------------------------------------------------------------------------------------
def _estimator(reduced: ReducedModel, lower: np.ndarray, upper: np.ndarray, n_added: int, min_coverage: float,
               test: ResidualTest) -> ContactEstimator:
    """A contact estimator for ``reduced`` whose last ``n_added`` bilateral inputs have no declared range yet; its
    estimates carry the one within-model test ``test`` (the skin's)."""
    b = reduced.n_bilateral - n_added
    lower = np.insert(np.asarray(lower, float), b, np.full(n_added, -np.inf))
    upper = np.insert(np.asarray(upper, float), b, np.full(n_added, np.inf))
    return ContactEstimator(min_coverage).fit(reduced, lower, upper, test)


def _fit(reduced: ReducedModel, lower: np.ndarray, upper: np.ndarray, fields: Sequence[DisplacementField],
         candidates: CandidateFields, names: Sequence[str], min_coverage: float, test: ResidualTest
         ) -> tuple[np.ndarray, tuple[ParameterEstimate, ...]]:
    """RSS (F,) mm^2 and contact-aware estimates of the fields with the candidates ``names`` appended to ``reduced``."""
    augmented = augment_reduced(reduced, candidates, list(names))
    estimator = _estimator(augmented, lower, upper, len(names), min_coverage, test)
    estimates = tuple(estimator.estimate(field) for field in fields)
    return np.array([np.nansum(e.residual**2) for e in estimates]), estimates


def trace_effect(
    reduced: ReducedModel,
    lower: np.ndarray,
    upper: np.ndarray,
    fields: Sequence[DisplacementField],
    candidates: CandidateFields,
    current: Sequence[ParameterEstimate],
    noise: Sequence[float],
    test: ResidualTest,
    alpha: float = DEFAULT_ALPHA,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    pairs: bool = True,
) -> Trace:
    """Rank the candidates by the residual they explain with the current model and decide what to add (module
    docstring, step 2: singles, then pairs).

    reduced, lower, upper: the current reduced model and its declared ranges (B + U,). fields: F fields.
    current: their contact-aware estimates with ``reduced``. noise: (F,) noise sigma per field, mm (weights of the
    RSS that ranks and tests the candidates). test: the skin's within-model test, which decides whether the fields
    are within the model with a candidate (the same test as before it, :func:`_decide`).
    pairs: fit pairs when no single candidate brings the fields within the model (False: singles only).
    Candidates already in ``reduced`` are skipped. Raises ModelError when no candidate is left.
    """
    if not len(fields) == len(current) == len(noise) >= 1:
        raise FieldError(f"need one estimate and one noise level per field, got {len(fields)} fields, "
                         f"{len(current)} estimates and {len(noise)} noise levels")
    names = [c.name for c in candidates.candidates if c.name not in reduced.names]
    if not names:
        raise ModelError("every candidate is already a parameter of the model: nothing left to trace")
    weights = 1.0 / np.asarray(noise, float) ** 2
    rss0 = np.array([np.nansum(e.residual**2) for e in current])
    n_seen = np.array([np.count_nonzero(np.isfinite(e.residual)) for e in current])
    dof0 = n_seen - np.array([fitted_unknowns(e) for e in current])
    dof1 = max(float(np.sum(dof0 - 1)), 1.0)
    q = len(fields)
    excess = float(weights @ rss0 - dof0.sum())
    rows = []
    for index, name in enumerate(names):
        rss, estimates = _fit(reduced, lower, upper, fields, candidates, [name], min_coverage, test)
        rows.append((name, rss, estimates))
        logger.info("trace %d/%d %s: weighted RSS %.1f", index + 1, len(names), name, weights @ rss)
    rows.sort(key=lambda row: float(weights @ row[1]))
    column = reduced.n_bilateral
    scores = []
    for name, rss, estimates in rows:
        candidate = candidates.candidates[candidates.index(name)]
        reduction = max(float(weights @ (rss0 - rss)), 0.0)
        variance = max(float(weights @ rss) / dof1, 1e-300)
        statistic = reduction / q / variance
        p_value = float(f_sf(statistic, q, dof1))
        scores.append(CandidateScore(
            name=name, kind=candidate.kind, unit=candidate.unit, description=candidate.description, rss_mm2=rss,
            weighted_rss=float(weights @ rss), explained=reduction / excess if excess > 0 else 0.0,
            f_statistic=statistic, p_value=p_value, p_adjusted=min(1.0, p_value * len(names)),
            values=np.array([e.values[column] for e in estimates]), std=np.array([e.std[column] for e in estimates]),
        ))
    best = scores[0]
    significant = best.p_adjusted < alpha
    variance = max(best.weighted_rss / dof1, 1e-300)
    decisiveness = (scores[1].weighted_rss - best.weighted_rss) / variance if len(scores) > 1 else np.inf
    threshold = float(chi2_isf(alpha, q))
    decisive = decisiveness > threshold
    _, within_after = _decide(rows[0][2], alpha)
    runner = scores[1].name if len(scores) > 1 else "-"
    pair_scores: tuple[PairScore, ...] = ()
    outcome, named, named_estimates = "unexplained", (), ()
    if not significant:
        reason = f"no candidate reduces the residual significantly (best {best.name}: adjusted p {best.p_adjusted:.3g})"
    elif best.explained < PARTIAL_MIN:
        # a candidate that tips a marginal field back under the test's threshold without removing most of the
        # excess (a 10 % stiffer panel region "explained" by a lock moved 0.0016 mm) explains nothing
        reason = (f"no candidate explains the residual: the best, {best.name}, removes {100 * best.explained:.0f} % "
                  f"of the residual beyond noise (needs {100 * PARTIAL_MIN:.0f} %)")
    elif not decisive:
        outcome = "ambiguous"
        reason = (f"{best.name} explains the residual but {runner} does almost as well "
                  f"(likelihood ratio {decisiveness:.1f} <= {threshold:.1f}): ambiguous")
    else:
        outcome = "found" if within_after else "partial"
        named, named_estimates = (best.name,), rows[0][2]
        reason = (f"{best.name} explains {100 * best.explained:.0f} % of the residual beyond noise "
                  f"(adjusted p {best.p_adjusted:.2g}; likelihood ratio to {runner} {decisiveness:.3g})")
        if not within_after and pairs and len(scores) > 1:
            pair_scores, pair, pair_reason = _trace_pairs(reduced, lower, upper, fields, candidates, scores, weights,
                                                          rss0, excess, dof0, alpha, min_coverage, test)
            if pair is not None:
                outcome, named, named_estimates, reason = "found", pair[0].names, pair[1], pair_reason
            else:
                reason += pair_reason
        if outcome == "partial":
            reason += ("; the fields stay outside the model with it: the model still lacks something near it, and "
                       "the effect is its nearest candidate (named, not added)")
    return Trace(
        scores=tuple(scores), rss_before_mm2=rss0, excess=excess, significant=significant,
        decisiveness=float(decisiveness), decisive_threshold=threshold, decisive=decisive, within_after=within_after,
        pairs=pair_scores, outcome=outcome, named=tuple(named), reason=reason,
        named_estimates=tuple(named_estimates),
    )


def _trace_pairs(
    reduced: ReducedModel, lower: np.ndarray, upper: np.ndarray, fields: Sequence[DisplacementField],
    candidates: CandidateFields, scores: Sequence[CandidateScore], weights: np.ndarray,
    rss0: np.ndarray, excess: float, dof0: np.ndarray, alpha: float, min_coverage: float, test: ResidualTest,
) -> tuple[tuple[PairScore, ...], tuple[PairScore, tuple[ParameterEstimate, ...]] | None, str]:
    """Fit the best single jointly with every other candidate; return the pairs (best first), the pair to take with
    its estimates (or None) and why (module docstring, step 2, "Pairs")."""
    first = scores[0]
    n_pairs = len(scores) - 1
    q = len(fields)
    dof2 = max(float(np.sum(dof0 - 2)), 1.0)
    column = reduced.n_bilateral
    fitted = []
    for second in scores[1:]:
        rss, estimates = _fit(reduced, lower, upper, fields, candidates, [first.name, second.name], min_coverage,
                              test)
        weighted = float(weights @ rss)
        variance = max(weighted / dof2, 1e-300)
        statistic = max(first.weighted_rss - weighted, 0.0) / q / variance
        values = np.array([[e.values[column], e.values[column + 1]] for e in estimates])
        std = np.array([[e.std[column], e.std[column + 1]] for e in estimates])
        fitted.append((PairScore(
            names=(first.name, second.name), rss_mm2=rss, weighted_rss=weighted,
            explained=float(weights @ (rss0 - rss)) / excess if excess > 0 else 0.0, f_statistic=statistic,
            p_adjusted=min(1.0, float(f_sf(statistic, q, dof2)) * n_pairs),
            within_after=_decide(estimates, alpha)[1], values=values, std=std,
        ), estimates))
        logger.info("trace pair %s + %s: weighted RSS %.1f", first.name, second.name, weighted)
    fitted.sort(key=lambda item: item[0].weighted_rss)
    pairs = tuple(item[0] for item in fitted)
    best = pairs[0]
    variance = max(best.weighted_rss / dof2, 1e-300)
    ratio = (pairs[1].weighted_rss - best.weighted_rss) / variance if len(pairs) > 1 else np.inf
    threshold = float(chi2_isf(alpha, q))
    label = f"{best.names[0]} + {best.names[1]}"
    if best.within_after and best.p_adjusted < alpha and ratio > threshold:
        return pairs, fitted[0], (f"no single candidate brings the fields within the model; {label} together do "
                                  f"(second effect adjusted p {best.p_adjusted:.2g}; likelihood ratio to the "
                                  f"runner-up pair {ratio:.3g})")
    if not best.within_after:
        return pairs, None, "; no pair brings the fields within the model either"
    if best.p_adjusted >= alpha:
        return pairs, None, (f"; {label} brings the fields within the model, but its second effect is not "
                             f"significant (adjusted p {best.p_adjusted:.2g}): only {first.name} is named")
    # within, significant, not decisive: ratio <= threshold is finite, so there is a runner-up pair
    return pairs, None, (f"; {label} and {' + '.join(pairs[1].names)} bring the fields within the model alike "
                         f"(likelihood ratio {ratio:.3g} <= {threshold:.3g}): only {first.name} is named")


# --- augmenting --------------------------------------------------------------------------------------------------
def effect_range(values: np.ndarray, std: np.ndarray) -> float:
    """Half width h of the symmetric range of a new parameter: RANGE_MARGIN x max(|v| + 3 std), rounded up to two
    significant digits (so that nearby estimates give the same range)."""
    half = RANGE_MARGIN * float(np.max(np.abs(values) + 3.0 * np.nan_to_num(std)))
    if not half > 0 or not np.isfinite(half):
        raise ModelError(f"cannot size a range from estimates {values} with std {std}")
    scale = 10.0 ** (np.floor(np.log10(half)) - 1)
    return float(np.ceil(half / scale - 1e-9) * scale)


def extend_ensemble(ensemble: Ensemble, reduced: ReducedModel, lower: np.ndarray, upper: np.ndarray) -> Ensemble:
    """The full-factorial ensemble of ``reduced`` from the one of a model without its new inputs.

    ensemble: a full-factorial Ensemble (ranks >= 0) whose names are a subset of ``reduced.names`` with the same
    unilateral parameters. lower, upper: (P_new,) ranges in ``reduced.names`` order; the old parameters keep theirs.
    The old members are the layer where every new parameter is 0 (reused as they are); only the min/max layers of the
    new parameters are solved (2 x M members for one new parameter). Members are ordered by rank (Table 1).
    """
    names = tuple(reduced.names)
    old = tuple(ensemble.names)
    missing = [n for n in old if n not in names]
    if missing:
        raise EnsembleError(f"ensemble parameters {missing} are not inputs of the extended model {names}")
    if old[ensemble.n_bilateral:] != names[reduced.n_bilateral:]:
        raise EnsembleError(f"unilateral parameters differ: ensemble {old[ensemble.n_bilateral:]}, "
                            f"model {names[reduced.n_bilateral:]}")
    if np.any(np.asarray(ensemble.rank) < 0):
        raise EnsembleError("only a full-factorial (training) ensemble can be extended; got random members")
    if ensemble.model_id != reduced.model_id:
        raise ModelIdMismatchError(
            f"ensemble model_id {ensemble.model_id!r} differs from the model's {reduced.model_id!r}")
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    old_columns = [names.index(n) for n in old]
    if not (np.allclose(lower[old_columns], ensemble.lower) and np.allclose(upper[old_columns], ensemble.upper)):
        raise EnsembleError("the old parameters' ranges must stay as in the ensemble")
    new_columns = [i for i, n in enumerate(names) if n not in old]
    m = ensemble.n_members

    def widen(array: np.ndarray) -> np.ndarray:
        out = np.zeros((m, len(names)))
        out[:, old_columns] = array
        return out

    blocks = [(widen(ensemble.commanded), widen(ensemble.effective), ensemble.contact_fraction, ensemble.reactions,
               np.asarray(ensemble.rank), ensemble.normal_displacement, ensemble.displacement)]
    levels = [(0.0, lower[c], upper[c]) for c in new_columns]
    for combination in itertools.product(*levels):
        if not any(combination):
            continue
        commanded = widen(ensemble.commanded)
        commanded[:, new_columns] = combination
        solved = solve_members(reduced, commanded)
        rank = np.asarray(ensemble.rank) + int(np.count_nonzero(combination))
        blocks.append((commanded, solved.effective, solved.contact_fraction, solved.reactions, rank,
                       solved.normal_displacement, solved.displacement))
        layer = {names[c]: float(v) for c, v in zip(new_columns, combination, strict=True)}
        logger.info("extended ensemble: layer %s solved (%d members)", layer, m)
    parts = [np.concatenate(items) for items in zip(*blocks, strict=True)]
    order = np.argsort(parts[4], kind="stable")
    commanded, effective, fraction, reactions, rank, normal, vectors = (p[order] for p in parts)
    return Ensemble(
        model_id=reduced.model_id, names=names, n_bilateral=reduced.n_bilateral, lower=lower, upper=upper,
        commanded=commanded, effective=effective, contact_fraction=fraction, reactions=reactions, rank=rank,
        normal_displacement=normal, displacement=vectors,
    )


def training_ensemble(bases: Bases) -> Ensemble:
    """The full-factorial ensemble of a bases file's reduced model (its members solved again: exact, seconds)."""
    reduced = bases.reduced_model
    commanded, rank = factorial_plan(bases.pca.lower_, bases.pca.upper_)
    return simulate_ensemble(reduced, commanded, rank, bases.pca.lower_, bases.pca.upper_)


# --- the loop ----------------------------------------------------------------------------------------------------
def close_loop(
    bases: Bases,
    fields: Sequence[DisplacementField],
    candidates: CandidateFields,
    ensemble: Ensemble | None = None,
    alpha: float = DEFAULT_ALPHA,
    default_noise_mm: float = DEFAULT_NOISE_MM,
    max_effects: int = 2,
    method: str = "contact",
    min_coverage: float = DEFAULT_MIN_COVERAGE,
) -> CloseLoopResult:
    """Find, add and report the effect the model lacks for F fields of one model (module docstring).

    bases: the current bases (with their reduced model). fields: F >= 1 displacement fields (N,) mm.
    candidates: candidate responses of the same model (:func:`hood_decomp.core.loop.candidates.candidate_fields`).
    ensemble: the full-factorial training ensemble of ``bases`` (its members are reused); None: solved again from
    the reduced model. default_noise_mm: noise of a field with unknown ``noise_rms``. max_effects: effects added at
    most, 1 or 2 (a pair of candidates for one missing effect). method: estimator of the before/after estimates
    ("contact" or "pca"); tracing is always contact-aware.
    """
    timings: dict[str, float] = {}
    start = time.perf_counter()
    if bases.reduced_model is None:
        raise BasisError("closing the loop needs bases with a reduced model (tracing is contact-aware)")
    if not fields:
        raise FieldError("close_loop needs at least one field")
    if candidates.normal.shape[0] != bases.skin.n_nodes:
        raise ModelIdMismatchError(f"candidate responses have {candidates.normal.shape[0]} skin nodes, the bases "
                              f"{bases.skin.n_nodes}: they come from another model")
    if max_effects not in (1, 2):
        raise ModelError(f"max_effects must be 1 (one candidate) or 2 (a pair may be added), got {max_effects}")
    noise = [noise_level(fd.noise_rms, default_noise_mm)[0] for fd in fields]
    before = tuple(estimate_field(bases, fd, method, min_coverage) for fd in fields)
    analyses_before, p_before, within_before = _analyse(bases, before, noise, alpha)
    timings["before_s"] = time.perf_counter() - start
    logger.info("before: residual RMS %s mm, within model: %s (p %.3g)",
                [round(a.rms_mm, 4) for a in analyses_before], within_before, p_before)

    start = time.perf_counter()
    reduced, lower, upper = bases.reduced_model, bases.pca.lower_, bases.pca.upper_
    # the tracing fits the candidates to the fields as the model's nodes moved, as estimate_field does (a scan's slide
    # taken out: core.method.surface_reading)
    nodes = tuple(node_field(bases, fd, min_coverage) for fd in fields)
    current = before if method == "contact" else tuple(
        _estimator(reduced, lower, upper, 0, min_coverage, bases.residual_test()).estimate(fd) for fd in nodes)
    trace = trace_effect(reduced, lower, upper, nodes, candidates, current, noise, bases.residual_test(), alpha=alpha,
                         min_coverage=min_coverage, pairs=max_effects == 2)
    traces = (trace,)
    timings["trace_s"] = time.perf_counter() - start

    if within_before or trace.outcome != "found":
        status = "within_model" if within_before else trace.outcome
        if within_before:
            message = "the residual is what the scan noise explains: nothing added"
        elif trace.outcome == "partial":
            shifts = _declared_shifts(bases, before, trace.named_estimates)
            message = (f"partial, nothing added: {trace.reason}. Adding it would move the declared estimates by up to "
                       f"{shifts:.3g} mm while the fields stay outside the model; look for the cause near "
                       f"{', '.join(trace.named)}")
        else:
            message = f"nothing added: {trace.reason}"
        return CloseLoopResult(
            status=status, message=message, before=before, analyses_before=analyses_before,
            within_model_before=within_before, p_value_before=p_before, traces=traces, added=(),
            bases_after=None, after=(), analyses_after=(), within_model_after=None, p_value_after=None,
            timings=timings,
        )

    added_names = list(trace.named)
    reduced = augment_reduced(bases.reduced_model, candidates, added_names)
    start = time.perf_counter()
    n_new = len(added_names)
    provisional = _estimator(reduced, lower, upper, n_new, min_coverage, bases.residual_test())
    estimates = [provisional.estimate(fd) for fd in nodes]
    b = bases.reduced_model.n_bilateral
    halves = [effect_range(np.array([e.values[b + j] for e in estimates]), np.array([e.std[b + j] for e in estimates]))
              for j in range(n_new)]
    new_lower = np.insert(np.asarray(lower, float), b, [-h for h in halves])
    new_upper = np.insert(np.asarray(upper, float), b, halves)
    old = ensemble if ensemble is not None else training_ensemble(bases)
    extended = extend_ensemble(old, reduced, new_lower, new_upper)
    timings["ensemble_s"] = time.perf_counter() - start
    start = time.perf_counter()
    bases_after = rebuilt_like(build_bases(extended, bases.skin, reduced, n_components=bases.pca.n_components,
                                                  explained_variance=bases.pca.explained_variance,
                                                  epsilon=bases.hierarchical.epsilon_), bases)
    if bases.scan_reading_bias is not None:  # the new basis' fields have their own reading bias, as a saved file
        bases_after = with_reading_bias(bases_after)
    timings["bases_s"] = time.perf_counter() - start
    start = time.perf_counter()
    after = tuple(estimate_field(bases_after, fd, method, min_coverage) for fd in fields)
    analyses_after, p_after, within_after = _analyse(bases_after, after, noise, alpha)
    timings["after_s"] = time.perf_counter() - start
    added = []
    for j, name in enumerate(added_names):
        candidate = candidates.candidates[candidates.index(name)]
        column = b + j
        added.append(AddedEffect(
            name=name, kind=candidate.kind, unit=candidate.unit, boundary=candidate.boundary,
            description=candidate.description, values=np.array([e.values[column] for e in after]),
            std=np.array([e.std[column] for e in after]), lower=-halves[j], upper=halves[j],
        ))
    summary = ", ".join(f"{a.name} ({', '.join(f'{v:+.4g}' for v in a.values)} {a.unit})" for a in added)
    message = (f"added {summary}; residual RMS {max(a.rms_mm for a in analyses_before):.4g} -> "
               f"{max(a.rms_mm for a in analyses_after):.4g} mm; within the model after: {within_after}")
    return CloseLoopResult(
        status="found", message=message, before=before, analyses_before=analyses_before,
        within_model_before=within_before, p_value_before=p_before, traces=tuple(traces), added=tuple(added),
        bases_after=bases_after, after=after, analyses_after=analyses_after, within_model_after=within_after,
        p_value_after=p_after, timings=timings,
    )
