"""Decomposition of a field into effects with the hierarchical basis (paper Fig. 2 steps 3-7, eqs. 6-8).

3. Subset: effects involving a parameter estimated at about zero cannot be present and are left out (a lifted
   unilateral boundary is kept: lifting is itself an effect relative to the nominal contact).
4. Least squares of the field (seen nodes) on the subset's independent basis fields.
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
from hood_decomp.errors import BasisError

# Step 5 removes effects contributing less than this fraction of the summed effect magnitudes.
DEFAULT_MIN_SHARE = 0.02
# Step 5 never removes an effect whose normal partial field has an RMS above this (mm): coarsening must not cost
# reconstruction quality beyond what a scan resolves.
DEFAULT_MAX_REMOVED_RMS_MM = 0.002
# Step 3: a parameter with |estimate| below max(this, 3 std) counts as zero.
DEFAULT_ZERO_TOL_MM = 0.01


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
) -> Decomposition:
    """Decompose one field (N,) mm, NaN where unseen, into effects (steps 3-6); see the module docstring.

    estimate: the parameter estimate of the same field (step 2), or None to start from every effect.
    Returns effects in decreasing share; contributions are (N,) in 0..1 and sum to 1 where D > 0.
    """
    n_nodes = basis.fields_.shape[1]
    values, valid = check_field(field, basis.model_id_, n_nodes, min_coverage)
    y = np.where(valid, values, 0.0)
    normal_all = valid_normal_matrix(basis.fields_, basis.gram_, valid)
    rhs_all = basis.fields_ @ y

    effects = np.flatnonzero(select_effects(basis, estimate, zero_tol_mm))
    while True:
        groups = _effect_field_indices(basis, effects)
        used = np.concatenate(groups)
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
