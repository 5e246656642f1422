"""Decomposition of a field into effects with the hierarchical basis (paper Fig. 2 steps 3-7, eqs. 6-8).

3. Subset: effects involving a parameter estimated at about zero cannot be present and are left out (a lifted
   unilateral boundary is kept: lifting is itself an effect relative to the nominal contact).
4. Least squares of the field (seen nodes) on the subset's independent basis fields. On a noisy field (one with an
   error model) the pre-factors are pulled toward those of the estimate's own state (:func:`anchored_coefficients`)
   with the weight n tau^2, tau a tenth of the field's node noise with its correlation (RMS of std x sqrt(g), g the
   node's correlation sum: a smoothed scan's noise reaches a smooth direction sqrt(g) times as strongly as white
   noise of the same std): a direction of the pre-factors that moves the field by less than tau RMS is the
   estimate's, not the noise's. Without it a lock's or buffer's partial displacement moved by up to half its peak
   with 1 um of node noise (their pairs are far from antisymmetric and nearly collinear with each other;
   benchmarks/RESULTS.md issue 15 run 18 C). A deviation from the paper's step 4 (docs/paper_comparison.md); a field
   without an error model keeps the paper's least squares.
5. Coarsening: the effect with the smallest contribution is removed and the fit repeated while that contribution is
   below ``min_share`` of the total and its partial field's RMS is below ``max_removed_rms_mm``. The contribution
   measure of this loop is the RMS of the effect's normal partial field, computed from the Gram matrix in O(F^2) per
   step, not O(N).
6. Partial displacements d_i = |c_i B_i + c_i^-1 B_i^-1| of the 3D basis fields (eq. 6), D = sum_i d_i (eq. 7),
   contributions d_i / D (eq. 8, 0 where D = 0), and each effect's share sum(d_i) / sum(D).
"""

from __future__ import annotations

import numpy as np

from hood_decomp.core.method.estimation import (
    DEFAULT_MIN_COVERAGE,
    check_field,
    residual_stats,
    solve_normal,
    valid_normal_matrix,
)
from hood_decomp.core.method.hierarchical import HierarchicalBasis
from hood_decomp.core.types import Decomposition, DisplacementField, EffectContribution, ParameterEstimate
from hood_decomp.errors import BasisError, FieldError

# Step 5 removes effects contributing less than this fraction of the summed effect magnitudes.
DEFAULT_MIN_SHARE = 0.02
# Step 5 never removes an effect whose normal partial field has an RMS above this (mm): coarsening must not cost
# reconstruction quality beyond what a scan resolves.
DEFAULT_MAX_REMOVED_RMS_MM = 0.002
# Step 3: a parameter with |estimate| below max(this, 3 std) counts as zero.
DEFAULT_ZERO_TOL_MM = 0.01
# Step 4 on a noisy field: a direction of the pre-factors that moves the field by less than this fraction of its
# node noise (RMS, with its correlation: :func:`prior_tau`) is taken from the estimate's state
# (:func:`anchored_coefficients`), not from the noise.
DEFAULT_PRIOR_NOISE_SHARE = 0.1


def select_effects(basis: HierarchicalBasis, estimate: ParameterEstimate | None, zero_tol_mm: float) -> np.ndarray:
    """Step 3: (E,) bool, the effects that can be present given the estimated parameter state."""
    keep = np.ones(len(basis.effect_names_), dtype=bool)
    if estimate is None:
        return keep
    if tuple(estimate.names) != tuple(basis.names_):
        raise BasisError(f"estimate parameters {estimate.names} differ from the basis parameters {basis.names_}")
    zero = (np.abs(estimate.values) <= np.maximum(zero_tol_mm, 3.0 * np.nan_to_num(estimate.std))) & ~estimate.lifted
    return ~np.any(basis.effect_mask_ & zero[None, :], axis=1)


def _effect_field_indices(basis: HierarchicalBasis, effects: np.ndarray) -> list[np.ndarray]:
    """Per effect, the indices of its independent basis fields."""
    out = []
    for e in effects:
        idx = basis.effect_fields_[e]
        idx = idx[idx >= 0]
        out.append(idx[basis.independent_[idx]])
    return out


def anchored_coefficients(basis: HierarchicalBasis, estimate: ParameterEstimate) -> np.ndarray:
    """(F,) the pre-factors the estimate's own state gives each basis field: LOADS 1; a single effect's pair (B at
    the state s+, B^-1 at s-, basis.field_states_) by the quadratic through u0, B and B^-1 at the estimated value
    clamped to [s-, s+] (exact for a response quadratic in its parameter); a lifted unilateral boundary its lowered
    field alone (the pad's support removed); an interaction 0. A field that is not independent (B^-1 = -B for a
    linear response) passes its share to the independent fields that span it (least squares over the whole skin)."""
    prior = np.zeros(basis.fields_.shape[0])
    for effect, fields in enumerate(basis.effect_fields_):
        fields = fields[fields >= 0]
        rank = int(basis.effect_rank_[effect])
        if rank > 1:
            continue
        share = np.ones(fields.size)
        if rank == 1:
            p = int(np.flatnonzero(basis.effect_mask_[effect])[0])
            states = basis.field_states_[fields, p]
            a = float(np.clip(estimate.values[p], states.min(), states.max()))
            if p >= basis.n_bilateral_ and estimate.lifted[p]:
                share = (states == states.min()).astype(float)
            elif fields.size == 1:
                share = np.array([a / states[0] if states[0] != 0 else 0.0])
            else:
                high, low = states
                share = np.array([a * (a - low) / (high * (high - low)), a * (a - high) / (low * (low - high))])
        prior[fields] = share
    fold = np.flatnonzero(~basis.independent_ & (prior != 0))
    if fold.size:  # a dependent field's share goes to the independent fields that span it (least squares)
        keep = np.flatnonzero(basis.independent_)
        carried = np.linalg.solve(basis.gram_[np.ix_(keep, keep)], basis.gram_[np.ix_(keep, fold)])
        prior[keep] += carried @ prior[fold]
        prior[fold] = 0.0
    return prior


def prior_tau(field: DisplacementField, valid: np.ndarray, share: float = DEFAULT_PRIOR_NOISE_SHARE) -> float:
    """tau (mm) of step 4's prior: ``share`` of the field's node noise over its seen nodes (valid (N,)) as a smooth
    direction sees it, the RMS of node std x sqrt(correlation sum); 0 for a field without an error model (a simulated
    field: the paper's least squares). With the std alone a smoothed scan's noise (correlation sums 5-10) still moved
    the locks' and buffers' partials 3-5x more than with it (benchmarks/RESULTS.md issue 15 run 19 D)."""
    errors = field.errors
    if errors.kind == "none":
        return 0.0
    variance, correlation = errors.node_variance(valid.size)
    return float(share * np.sqrt(np.mean((variance * correlation)[valid])))


def _partial_displacement(basis: HierarchicalBasis, coeff: np.ndarray, effect: int) -> np.ndarray:
    """Eq. (6): d_i = |c_i B_i + c_i^-1 B_i^-1| per node (N,) mm, from the 3D basis fields."""
    idx = basis.effect_fields_[effect]
    idx = idx[idx >= 0]
    return np.linalg.norm(np.tensordot(coeff[idx], basis.fields_3d_[idx], axes=1), axis=1)


def decompose(
    basis: HierarchicalBasis,
    field: DisplacementField,
    estimate: ParameterEstimate | None = None,
    min_share: float = DEFAULT_MIN_SHARE,
    zero_tol_mm: float = DEFAULT_ZERO_TOL_MM,
    min_coverage: float = DEFAULT_MIN_COVERAGE,
    max_removed_rms_mm: float = DEFAULT_MAX_REMOVED_RMS_MM,
    tau_mm: float | None = None,
) -> Decomposition:
    """Decompose one field (N,) mm, NaN where unseen, into effects (steps 3-6); see the module docstring.

    estimate: the parameter estimate of the same field (step 2), or None to start from every effect.
    tau_mm: step 4's prior (module docstring): the pre-factors c minimise |y - F c|^2 + n tau^2 |c - c0|^2 over the
    n seen nodes, c0 the estimate's (:func:`anchored_coefficients`); None: :func:`prior_tau` of the field (0, the
    paper's least squares, for a field without an error model); always 0 without an estimate.
    Returns effects in decreasing share; contributions are (N,) in 0..1 and sum to 1 where D > 0.
    """
    n_nodes = basis.fields_.shape[1]
    values, valid = check_field(field, basis.model_id_, n_nodes, min_coverage)
    y = np.where(valid, values, 0.0)
    normal_all = valid_normal_matrix(basis.fields_, basis.gram_, valid)
    rhs_all = basis.fields_ @ y
    tau = 0.0 if estimate is None else prior_tau(field, valid) if tau_mm is None else float(tau_mm)
    if not (np.isfinite(tau) and tau >= 0.0):
        raise FieldError(f"tau_mm must be a finite number >= 0 mm, got {tau_mm}")
    pull = float(valid.sum()) * tau**2
    prior = anchored_coefficients(basis, estimate) if pull > 0 else np.zeros(basis.fields_.shape[0])

    effects = np.flatnonzero(select_effects(basis, estimate, zero_tol_mm))
    while True:
        groups = _effect_field_indices(basis, effects)
        used = np.concatenate(groups)
        if pull > 0:
            coeff = np.linalg.solve(normal_all[np.ix_(used, used)] + pull * np.eye(used.size),
                                    rhs_all[used] + pull * prior[used])
        else:
            coeff, _ = solve_normal(normal_all[np.ix_(used, used)], rhs_all[used], "hierarchical pre-factors")
        if effects.size <= 1:
            break
        # RMS of each effect's normal partial field from the full Gram matrix: c^T G c / N.
        position = {f: i for i, f in enumerate(used)}
        magnitude = np.array([
            np.sqrt(max(float(c @ basis.gram_[np.ix_(g, g)] @ c), 0.0) / n_nodes)
            for g in groups
            for c in [coeff[[position[f] for f in g]]]
        ])
        smallest = int(np.argmin(magnitude))
        if magnitude[smallest] >= min_share * magnitude.sum() or magnitude[smallest] > max_removed_rms_mm:
            break
        effects = np.delete(effects, smallest)

    full = np.zeros(basis.fields_.shape[0])
    full[used] = coeff
    reconstruction = full @ basis.fields_
    residual, rms, _ = residual_stats(values, reconstruction, valid)
    partial = np.array([_partial_displacement(basis, full, e) for e in effects])
    total = partial.sum(axis=0)
    contribution = np.divide(partial, total, out=np.zeros_like(partial), where=total > 0)
    grand = float(total.sum())
    results = [
        EffectContribution(
            name=basis.effect_names_[e],
            parameters=basis.effect_parameters(int(e)),
            partial_displacement=partial[i],
            contribution=contribution[i],
            share=float(partial[i].sum() / grand) if grand > 0 else 0.0,
        )
        for i, e in enumerate(effects)
    ]
    results.sort(key=lambda r: -r.share)
    return Decomposition(
        model_id=basis.model_id_,
        effects=tuple(results),
        reconstruction=reconstruction,
        residual=residual,
        reconstruction_rms=rms,
    )


def reconstruct_members(basis: HierarchicalBasis, values: np.ndarray) -> np.ndarray:
    """Least-squares reconstruction of complete fields (M, N) mm with the whole basis (Fig. 10) -> (M, N) mm."""
    independent = np.flatnonzero(basis.independent_)
    fields = basis.fields_[independent]
    coeff = np.linalg.solve(basis.gram_[np.ix_(independent, independent)], fields @ np.asarray(values, float).T)
    return coeff.T @ fields
