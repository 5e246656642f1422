"""Recurring residuals over many parts -> effects the model lacks: traced to an FE candidate, or offered as a
**measured effect** (a basis field with a name, learned from the parts, with no boundary behind it).

Input: the residual fields r_i (N,) mm (NaN where unseen) of the M parts the model does not explain, their noise
sigma_i and their declared-parameter estimates. Steps, repeated for up to ``max_modes`` modes:

1. **Mode**: the leading mode u (N,) of the noise-weighted residuals y_i = r_i / sigma_i by a rank-1 fit with missing
   data (alternating least squares over the seen nodes only: a_i = <y_i, u>_i / <u, u>_i, u = sum a_i y_i / sum a_i^2
   node by node). Per part, its amplitude a_i with std 1 / sqrt(<u, u>_i) (in noise units).
2. **Judged against noise, cross-validated**: u is learned on one half of the parts (every other part in time order)
   and judged on the other, whose noise it has never seen: under "no recurring mode" z_i = a_i / std_i are standard
   normal, so sum z_i^2 over the judging half is chi-square with one degree of freedom per part. The mode is real
   when its p-value is below ``alpha`` and it is present (|z| > 3) in at least ``min_parts`` parts. A part carries a
   mode when its |z| > 3 and the mode removes at least half of the part's residual energy beyond noise.
3. **Traced to the FE candidates first**: each candidate's unit response c_k becomes a *template* t_k, what the
   contact-aware estimator leaves of it in the residual (the residual of a typical part's field plus 0.1 mm c_k,
   minus that of the part, per mm), with its leak g_k (P,) into the declared estimates. Jointly over the parts, the
   candidate whose template removes the most residual energy is the explanation when it removes at least
   :data:`TRACE_MIN` of what the free mode u removes; its per-part magnitude is the least-squares amplitude on t_k.
4. Otherwise the mode is offered as a **measured effect**. The residual shows only the part of the effect the declared
   fields cannot absorb (u = P_perp v); the absorbed part is unobservable from residuals alone. It is restored by the
   one assumption a local defect allows: the effect vanishes away from its support (nodes where the smoothed |u|
   exceeds :data:`SUPPORT_FRACTION` of its peak, grown by two rings, then grown to where the restored effect's tail
   exceeds :data:`TAIL_FRACTION` of its peak, at most half the skin), so v = u + J^T beta with beta fitting -u on the
   other nodes (J: d field / d state of the declared parameters at a typical state, contact included), and v = 0
   off the support. The effect's template and leak come from the estimator as in step 3 (per part, with the part's
   own seen nodes), so its per-part amplitude also corrects the declared estimates (their bias by the effect).
5. **Before/after, cross-validated**: v learned on the learning half; on the judging half's affected parts the residual
   RMS before and after removing a_i t_v (compared with the RMS the error model expects, sigma), and the corrected
   declared estimates, values - a_i g_v.

The residual of each explained part is deflated by its fitted mode before the next mode is sought. Nothing is offered
when no mode passes step 2 (a shift without a recurring effect). Bases with the effect as a parameter without a
boundary: :func:`augmented_bases`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.loop.candidates import Candidate, CandidateFields, augment_reduced
from hood_decomp.core.loop.close_loop import effect_range, extend_ensemble
from hood_decomp.core.method.bases import Bases, build_bases, rebuilt_like
from hood_decomp.core.method.distributions import chi2_sf
from hood_decomp.core.method.residual import DEFAULT_ALPHA, skin_adjacency
from hood_decomp.core.types import DisplacementField, Ensemble
from hood_decomp.errors import FieldError

logger = logging.getLogger(__name__)

#: a candidate explains a mode when its template removes at least this fraction of what the free mode removes
TRACE_MIN = 0.9
#: support of a measured effect: smoothed |u| above this fraction of its peak (then grown by two rings) ...
SUPPORT_FRACTION = 0.25
#: ... then grown to where the restored effect's smoothed magnitude exceeds this fraction of its peak
TAIL_FRACTION = 0.03
RESTORE_ITERATIONS = 4
#: template step (mm of a candidate or effect), small enough for the contact state not to change
TEMPLATE_STEP_MM = 0.1
#: |a_i| / std_i above which a part carries a mode
PRESENT_Z = 3.0


@dataclass(frozen=True)
class Template:
    """What the estimator makes of a unit input: residual (N,) mm per unit, leak (P,) change of the declared
    estimates per unit."""

    residual: np.ndarray
    leak: np.ndarray


@dataclass(frozen=True)
class FoundMode:
    """One recurring mode. kind: "candidate" (traced; ``name`` the candidate, unit mm or N) or "measured" (``name``
    "measured_<k>", ``field`` the restored basis field v (N,) mm per unit amplitude, peak 1). mode: (N,) the free
    mode u (unit norm). template: the shape removed from the residuals (N,). parts: (M,) bool, parts carrying it;
    amplitude, std: (M,) per part (unit of the input; NaN where not fitted). explained: energy the best candidate
    removes relative to the free mode. p_value: cross-validated chi-square test; n_learn, n_judge: halves' sizes.
    rms_before, rms_after: (J,) residual RMS of the judging half's affected parts before/after, mm; expected_rms:
    (J,) what their error model expects; judged: (M,) bool, those parts. values_after: (M, P) declared estimates
    with the mode's leak removed (NaN rows where the part does not carry it)."""

    kind: str
    name: str
    field: np.ndarray
    mode: np.ndarray
    template: np.ndarray
    parts: np.ndarray
    amplitude: np.ndarray
    std: np.ndarray
    explained: float
    candidate_scores: tuple[tuple[str, float], ...]
    p_value: float
    n_learn: int
    n_judge: int
    judged: np.ndarray
    rms_before: np.ndarray
    rms_after: np.ndarray
    expected_rms: np.ndarray
    values_after: np.ndarray


@dataclass(frozen=True)
class RecurringResult:
    """modes: what was found, in order; message: one sentence; n_outside: parts analysed (outside the model)."""

    modes: tuple[FoundMode, ...]
    n_outside: int
    message: str

    @property
    def measured(self) -> tuple[FoundMode, ...]:
        return tuple(m for m in self.modes if m.kind == "measured")


def templates(bases: Bases, state: np.ndarray, fields: np.ndarray) -> list[Template]:
    """Templates (module docstring, step 3) of unit input fields (K, N) mm at the declared state ``state`` (P,) mm."""
    reduced = bases.reduced_model
    if reduced is None:
        raise FieldError("tracing recurring residuals needs bases with a reduced model")
    estimator = bases.contact_estimator(0.0)
    reference = solve_members(reduced, np.asarray(state, float)[None, :]).normal_displacement[0]

    def estimate(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        result = estimator.estimate(DisplacementField(bases.model_id, values, 1.0, float("nan")))
        return result.residual, result.values

    base_residual, base_values = estimate(reference)
    out = []
    for column in np.atleast_2d(fields):
        residual, values = estimate(reference + TEMPLATE_STEP_MM * column)
        out.append(Template((residual - base_residual) / TEMPLATE_STEP_MM, (values - base_values) / TEMPLATE_STEP_MM))
    return out


@dataclass(frozen=True)
class PartFit:
    """A shape fitted to R parts' residuals with each part's own seen nodes: amplitude, std (R,) in the shape's unit;
    leak (R, P): change of the declared estimates per unit; after: (R, N) residuals with the fitted shape removed."""

    amplitude: np.ndarray
    std: np.ndarray
    leak: np.ndarray
    after: np.ndarray


def part_fits(bases: Bases, state: np.ndarray, shape: np.ndarray, residuals: np.ndarray, noise: np.ndarray
              ) -> PartFit:
    """Fit ``shape`` (N,) mm per unit to each residual (R, N) through the estimator with that part's seen nodes: the
    template of part i is what the estimator leaves of the shape on the nodes part i shows (occlusions change it)."""
    reduced = bases.reduced_model
    estimator = bases.contact_estimator(0.0)
    reference = solve_members(reduced, np.asarray(state, float)[None, :]).normal_displacement[0]
    rows = len(residuals)
    amplitude, std = np.zeros(rows), np.zeros(rows)
    leak = np.zeros((rows, len(bases.names)))
    after = np.array(residuals, float, copy=True).reshape(rows, -1)
    for i, residual in enumerate(after):
        seen = np.isfinite(residual)

        def estimate(values: np.ndarray, seen: np.ndarray = seen) -> tuple[np.ndarray, np.ndarray]:
            masked = np.where(seen, values, np.nan)
            result = estimator.estimate(DisplacementField(bases.model_id, masked, float(seen.mean()), float("nan")))
            return np.nan_to_num(result.residual), result.values

        base_residual, base_values = estimate(reference)
        moved_residual, moved_values = estimate(reference + TEMPLATE_STEP_MM * shape)
        template = (moved_residual - base_residual) / TEMPLATE_STEP_MM
        norm = float(template @ template)
        amplitude[i] = float(np.nan_to_num(residual) @ template) / max(norm, 1e-300)
        std[i] = noise[i] / np.sqrt(max(norm, 1e-300))
        leak[i] = (moved_values - base_values) / TEMPLATE_STEP_MM
        after[i] = np.where(seen, residual - amplitude[i] * template, np.nan)
    return PartFit(amplitude, std, leak, after)


def _fit(y: np.ndarray, seen: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-part least-squares amplitude of ``shape`` (N,) in y (M, N) over the seen nodes, and its std (units of y's
    noise, 1 per node)."""
    norm = seen.astype(float) @ shape**2
    amplitude = np.where(norm > 0, (np.where(seen, y, 0.0) @ shape) / np.maximum(norm, 1e-300), np.nan)
    return amplitude, np.where(norm > 0, 1.0 / np.sqrt(np.maximum(norm, 1e-300)), np.nan)


def leading_mode(y: np.ndarray, seen: np.ndarray, iterations: int = 60) -> np.ndarray:
    """Rank-1 mode u (N,) of y (M, N) with missing data (``seen`` False), unit norm, largest |u| positive."""
    filled = np.where(seen, y, 0.0)
    u = np.linalg.svd(filled, full_matrices=False)[2][0]
    weights = seen.astype(float)
    for _ in range(iterations):
        a = (filled @ u) / np.maximum(weights @ u**2, 1e-300)
        u_new = (a @ filled) / np.maximum(a**2 @ weights, 1e-300)
        u_new /= max(np.linalg.norm(u_new), 1e-300)
        if np.linalg.norm(u_new - u) < 1e-10:
            u = u_new
            break
        u = u_new
    return u * np.sign(u[np.argmax(np.abs(u))])


def _support(bases: Bases, values: np.ndarray, fraction: float) -> np.ndarray:
    """Nodes where the one-ring mean of |values| exceeds ``fraction`` of its peak, grown by two rings."""
    ring = skin_adjacency(bases.skin) + sp.identity(bases.skin.n_nodes, format="csr")
    count = np.asarray(ring.sum(axis=1)).ravel()
    smooth = (ring @ np.abs(values)) / count
    support = smooth >= fraction * smooth.max()
    for _ in range(2):
        support = (ring @ support.astype(float)) > 0
    return support


def declared_jacobian(bases: Bases, state: np.ndarray) -> np.ndarray:
    """d field / d state (P, N) mm/mm of the declared parameters at ``state`` (P,) mm, by central differences of the
    exact contact solution (TEMPLATE_STEP_MM): the fields a part's estimate absorbs a defect into."""
    reduced = bases.reduced_model
    state = np.asarray(state, float)
    steps = TEMPLATE_STEP_MM * np.eye(state.size)
    up = solve_members(reduced, state[None, :] + steps).normal_displacement
    down = solve_members(reduced, state[None, :] - steps).normal_displacement
    return (up - down) / (2 * TEMPLATE_STEP_MM)


def restore_field(bases: Bases, mode: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The effect v (N,) (peak 1) whose non-absorbed part is ``mode``, assuming it vanishes off its support (module
    docstring, step 4); and the support (N,) bool.

    The support starts where the mode is large and grows to where the restored effect is (its tail above
    :data:`TAIL_FRACTION` of its peak), a few times, never beyond half the skin (the rest must pin the fit)."""
    jacobian = declared_jacobian(bases, state)
    support = _support(bases, mode, SUPPORT_FRACTION)
    for _ in range(RESTORE_ITERATIONS):
        beta = np.linalg.lstsq(jacobian[:, ~support].T, -mode[~support], rcond=None)[0]
        full = mode + beta @ jacobian
        grown = support | _support(bases, full, TAIL_FRACTION)
        if grown.sum() > 0.5 * grown.size or np.array_equal(grown, support):
            break
        support = grown
    beta = np.linalg.lstsq(jacobian[:, ~support].T, -mode[~support], rcond=None)[0]
    field = np.where(support, mode + beta @ jacobian, 0.0)
    return field / field[np.argmax(np.abs(field))], support


def _carrying(z: np.ndarray, y: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Parts that carry a mode: its amplitude is significant (|z| > PRESENT_Z) and it removes at least half of the
    part's residual energy beyond noise (a part with another effect projects on any mode at high resolution)."""
    excess = np.sum(y**2, axis=1) - seen.sum(axis=1)
    return (np.abs(z) > PRESENT_Z) & (z**2 >= 0.5 * excess)


def _halves(index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return index[0::2], index[1::2]


def analyse_recurring(
    bases: Bases,
    residuals: np.ndarray,
    noise: np.ndarray,
    values: np.ndarray,
    state: np.ndarray,
    candidates: CandidateFields | None = None,
    alpha: float = DEFAULT_ALPHA,
    max_modes: int = 3,
    min_parts: int = 5,
) -> RecurringResult:
    """Recurring modes of the residuals (M, N) mm of M parts outside the model (module docstring).

    noise: (M,) sigma per part, mm. values: (M, P) their declared estimates, mm. state: (P,) a typical declared state
    (e.g. the median estimate of the shift), where templates are taken. candidates: FE candidate responses (None:
    nothing can be traced; every mode is offered as measured). Returns the modes in the order found.
    """
    residuals = np.atleast_2d(np.asarray(residuals, float))
    m, n = residuals.shape
    if n != bases.skin.n_nodes:
        raise FieldError(f"residuals have {n} nodes, the bases' skin {bases.skin.n_nodes}")
    noise = np.asarray(noise, float)
    if noise.shape != (m,) or not np.all(noise > 0):
        raise FieldError(f"noise must be ({m},) positive values, got shape {noise.shape}")
    values = np.asarray(values, float)
    seen = np.isfinite(residuals)
    y = np.where(seen, residuals, 0.0) / noise[:, None]
    cand_templates = [] if candidates is None else templates(bases, state, candidates.normal.T)
    modes: list[FoundMode] = []
    active = np.arange(m)
    for k in range(max_modes):
        if active.size < 2 * min_parts:
            break
        learn, judge = _halves(active)
        u = leading_mode(y[learn], seen[learn])
        a, s = _fit(y[judge], seen[judge], u)
        statistic = float(np.nansum((a / s) ** 2))
        p_value = float(chi2_sf(statistic, judge.size))
        present = np.abs(a / s) > PRESENT_Z
        logger.info("recurring mode %d: chi2 %.1f over %d judging parts (p %.3g), present in %d", k + 1, statistic,
                    judge.size, p_value, int(present.sum()))
        if not (p_value < alpha and present.sum() * 2 >= min_parts):
            break
        u_all = leading_mode(y[active], seen[active])
        a_u, s_u = _fit(y[active], seen[active], u_all)
        carrying = _carrying(a_u / s_u, y[active], seen[active])
        free_energy = float(np.nansum((a_u / s_u)[carrying] ** 2))
        scores = []
        for index, template in enumerate(cand_templates):
            a_t, s_t = _fit(y[active], seen[active], template.residual)
            scores.append((candidates.names[index], float(np.nansum((a_t / s_t)[carrying] ** 2)) / free_energy))
        scores.sort(key=lambda item: -item[1])
        explained = scores[0][1] if scores else 0.0
        if explained >= TRACE_MIN:
            kind, name = "candidate", scores[0][0]
            field = candidates.normal[:, candidates.index(name)]
            learned = field  # a candidate's shape is known: nothing is learned from the parts
        else:
            kind, name = "measured", f"measured_{sum(mode.kind == 'measured' for mode in modes) + 1}"
            field = restore_field(bases, u_all, state)[0]
            learned = restore_field(bases, u, state)[0]
        # cross-validated before/after on the judging half's carrying parts, with the shape of the learning half
        a_j, s_j = _fit(y[judge], seen[judge], u)
        rows = judge[_carrying(a_j / s_j, y[judge], seen[judge])]
        fit = part_fits(bases, state, learned, residuals[rows], noise[rows])
        rms_before = np.sqrt(np.nanmean(residuals[rows] ** 2, axis=1))
        rms_after = np.sqrt(np.nanmean(fit.after**2, axis=1))
        # final per-part amplitudes with the shape from all parts, in the input's unit
        parts = np.zeros(m, dtype=bool)
        parts[active[carrying]] = True
        fit = part_fits(bases, state, field, residuals[parts], noise[parts])
        amplitude = np.full(m, np.nan)
        std = np.full(m, np.nan)
        amplitude[parts], std[parts] = fit.amplitude, fit.std
        values_after = np.full_like(values, np.nan)
        values_after[parts] = values[parts] - fit.amplitude[:, None] * fit.leak
        template = templates(bases, state, field[None, :])[0].residual
        judged = np.zeros(m, dtype=bool)
        judged[rows] = True
        modes.append(FoundMode(
            kind=kind, name=name, field=np.asarray(field, float), mode=u_all, template=template,
            parts=parts, amplitude=amplitude, std=std, explained=explained, candidate_scores=tuple(scores[:5]),
            p_value=p_value, n_learn=learn.size, n_judge=judge.size, judged=judged, rms_before=rms_before,
            rms_after=rms_after, expected_rms=noise[rows], values_after=values_after,
        ))
        logger.info("recurring mode %d: %s %s in %d parts (best candidate removes %.0f %% of the mode's energy)",
                    k + 1, kind, name, int(parts.sum()), 100 * explained)
        # deflate: remove each carrying part's fitted mode, keep only parts still outside the model
        residuals = residuals.copy()
        residuals[parts] = fit.after
        y = np.where(seen, residuals, 0.0) / noise[:, None]
        excess = np.nansum(y**2, axis=1) - seen.sum(axis=1)
        still = chi2_sf(np.nansum(y**2, axis=1), seen.sum(axis=1)) < alpha
        active = np.flatnonzero(still & (excess > 0))
    if not modes:
        message = "no recurring residual mode beyond noise: nothing to add"
    else:
        message = "; ".join(f"{mode.name} ({mode.kind}) in {int(mode.parts.sum())} parts" for mode in modes)
    return RecurringResult(tuple(modes), m, message)


def effect_fields(bases: Bases, modes: tuple[FoundMode, ...]) -> CandidateFields:
    """Measured effects as candidate-like inputs (normal response per unit amplitude; no pad motion), so that
    :func:`~hood_decomp.core.loop.candidates.augment_reduced` appends them to a reduced model."""
    reduced = bases.reduced_model
    if reduced is None:
        raise FieldError("bases without a reduced model cannot gain a measured effect")
    normal = np.stack([mode.field for mode in modes], axis=1)
    return CandidateFields(
        candidates=tuple(Candidate(mode.name, "", "measured", (0.0, 0.0, 1.0),
                                   f"measured effect learned from {int(mode.parts.sum())} parts") for mode in modes),
        normal=normal, vectors=bases.skin.normals[:, :, None] * normal[:, None, :],
        pad=np.zeros((len(reduced.k), len(modes))), dropped=())


def augmented_bases(bases: Bases, ensemble: Ensemble, modes: tuple[FoundMode, ...]) -> Bases:
    """Bases rebuilt with measured effects as parameters without a boundary (range +- the close-loop margin over
    their per-part amplitudes): the ensemble gains their min/max layers, the PCA and the hierarchical basis are built
    again. The rebuilt bases name the effects (``Bases.measured_effects``, with those of ``bases``): every estimate
    marks them and reports each effect's amplitude as a parameter, and
    :func:`~hood_decomp.core.method.correction.plan_correction` never moves a boundary for them."""
    fields = effect_fields(bases, modes)
    names = [mode.name for mode in modes]
    reduced = augment_reduced(bases.reduced_model, fields, names)
    b = bases.reduced_model.n_bilateral
    halves = [effect_range(mode.amplitude[mode.parts], mode.std[mode.parts]) for mode in modes]
    lower = np.insert(np.asarray(bases.pca.lower_, float), b, [-h for h in halves])
    upper = np.insert(np.asarray(bases.pca.upper_, float), b, halves)
    extended = extend_ensemble(ensemble, reduced, lower, upper)
    rebuilt = build_bases(extended, bases.skin, reduced, n_components=bases.pca.n_components,
                          explained_variance=bases.pca.explained_variance, epsilon=bases.hierarchical.epsilon_)
    return replace(rebuilt_like(rebuilt, bases), measured_effects=(*bases.measured_effects, *names))
