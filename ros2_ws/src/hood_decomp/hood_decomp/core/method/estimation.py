"""Parameter estimation with the PCA basis (paper eqs. 4-5), and the field checks every estimator shares.

The least-squares fit uses the valid (finite) nodes only: an unseen node is missing data, not a zero displacement.
The normal matrix over the valid nodes is the full-field Gram matrix minus the unseen nodes' part, so a fit costs
O(K N) for the right-hand side and O(K^2 N_unseen) for the correction instead of O(K^2 N).
"""

from __future__ import annotations

import numpy as np

from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.method.residual import ResidualTest, check_residual, node_variance, split_level
from hood_decomp.core.types import DisplacementField, FieldErrorModel, ModelCheck, ParameterEstimate
from hood_decomp.errors import FieldError, ModelIdMismatchError

# A field must show at least this fraction of the skin nodes; below it the fit extrapolates from a patch.
DEFAULT_MIN_COVERAGE = 0.2
# A unilateral boundary whose estimated reaction is below this fraction of its largest ensemble reaction is lifted.
LIFTED_REACTION_FRACTION = 0.01


def check_field(
    field: DisplacementField, model_id: str, n_nodes: int, min_coverage: float = DEFAULT_MIN_COVERAGE
) -> tuple[np.ndarray, np.ndarray]:
    """Validate a field against a basis; return ``(values (N,) mm, valid (N,) bool)``.

    Raises ModelIdMismatchError for another model's field, FieldError for a wrong length, inf values, no finite value,
    a coverage below ``min_coverage`` or a bad error model (:meth:`FieldErrorModel.validate`).
    """
    if field.model_id != model_id:
        raise ModelIdMismatchError(f"field model_id {field.model_id!r} does not match the bases' model_id {model_id!r}")
    values = np.asarray(field.normal_displacement, dtype=float)
    if values.ndim != 1 or values.shape[0] != n_nodes:
        raise FieldError(f"field has shape {values.shape}, expected ({n_nodes},) (one value per visible skin node)")
    if np.any(np.isinf(values)):
        raise FieldError(f"field holds {int(np.isinf(values).sum())} inf values; unseen nodes must be NaN")
    field.errors.validate(n_nodes)
    valid = np.isfinite(values)
    n_valid = int(valid.sum())
    if n_valid == 0:
        raise FieldError("field has no finite value (all NaN)")
    coverage = n_valid / n_nodes
    if coverage < min_coverage:
        raise FieldError(f"field coverage {coverage:.3f} is below the minimum {min_coverage:.3f}")
    return values, valid


def valid_normal_matrix(fields: np.ndarray, gram: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Normal matrix over the valid nodes: fields (K, N), gram (K, K) = fields @ fields.T, valid (N,) -> (K, K)."""
    unseen = ~valid
    n_unseen = int(unseen.sum())
    if n_unseen == 0:
        return gram
    if n_unseen < valid.size // 2:
        part = fields[:, unseen]
        return gram - part @ part.T
    part = fields[:, valid]
    return part @ part.T


def solve_normal(normal: np.ndarray, rhs: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Solve the normal equations; return ``(coefficients, inverse normal matrix)``.

    Raises FieldError when the valid nodes do not determine the coefficients (singular normal matrix). The test is
    made on the matrix scaled to unit diagonal, so basis fields of very different size (a 500 mm^2 field beside a
    3 mm^2 one) are judged by the angles between them, not by their norms.
    """
    scale = np.sqrt(np.clip(np.diag(normal), 0.0, None))
    scale[scale == 0.0] = 1.0
    eigval, eigvec = np.linalg.eigh(normal / np.outer(scale, scale))
    if eigval.size and eigval[0] <= 1e-12 * max(eigval[-1], 1e-300):
        raise FieldError(f"the seen nodes do not determine the {what} (normal matrix is singular)")
    inverse = ((eigvec / eigval) @ eigvec.T) / np.outer(scale, scale)
    return inverse @ rhs, inverse


def residual_stats(
    values: np.ndarray, reconstruction: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, float, float]:
    """Residual (N,) mm, NaN where unseen, with its RMS and max-abs over the seen nodes."""
    residual = np.where(valid, values - reconstruction, np.nan)
    seen = residual[valid]
    return residual, float(np.sqrt(np.mean(seen**2))), float(np.max(np.abs(seen)))


def judge(
    residual: np.ndarray, design: np.ndarray, errors: FieldErrorModel, test: ResidualTest | None, model_mm: float,
    span: np.ndarray | None = None,
) -> tuple[ModelCheck, np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
    """The within-model test of a fit on ``design`` (N, p) (``test``'s when given, else the level test without
    smooth modes) and the low-rank field errors (N, k) the covariance adds (the field's registration modes and the
    calibrated model's discrepancy modes, :meth:`ResidualTest.error_modes`; None without either). span: (N, q) all the
    fields the model can make, whose directions the smooth test leaves out (default: the design).

    Without a ``test`` the estimator has no skin, so a registration covariance cannot reach the nodes and is left
    out (the covariance is then that of the field given its registration); the verbs and nodes always estimate
    through the bases (estimate_field), which pass the skin's test. Close-loop's tracing estimates are made so.
    Third: the discrepancy as measured and its rows' noise, (D, W) (:meth:`ResidualTest.discrepancy_pair`), which
    the covariance nets along its gains; None when the bases state no noise (D is then among the error modes)."""
    if test is None:
        return check_residual(residual, design, errors, model_mm=model_mm), None, None
    return (test.check(residual, design if span is None else span, errors, model_mm), test.error_modes(errors),
            test.discrepancy_pair())


def parameter_covariance(
    design: np.ndarray, inverse: np.ndarray, valid: np.ndarray, errors: FieldErrorModel, scale: float,
    model_mm: float, registration: np.ndarray | None,
    discrepancy: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Covariance (q, q) of least-squares coefficients theta = inverse @ design[valid].T @ y (design (N, q)).

    The sandwich G Sigma G^T with G = inverse X^T over the valid nodes and the node covariance Sigma = noise *
    diag(v g) + (model^2 + bias) I + U U^T (error model variances v, correlation sums g, the level ``scale`` split
    into noise and the making's bias by :func:`split_level`, low-rank field errors U (N, k): the registration's and
    the calibrated model's discrepancy, :meth:`ResidualTest.error_modes`): the correlation enters
    through g (exact for coefficients whose gain is smooth on the correlation scale). A uniform error model costs
    nothing beyond the normal matrix' inverse.

    discrepancy: (D, W) the calibrated model's discrepancy as measured and its rows' expected noise
    (:meth:`ResidualTest.discrepancy_pair`): along each coefficient's gain g, g^T (D D^T - W W^T) g is the unbiased
    estimate of the model error the rows saw (their noise is the calibration entries', not the part's: the part's
    own is in the first term), floored at 0; the rows as measured are scaled per coefficient to that variance,
    S G D D^T G^T S, which keeps their correlations and a covariance. Clipping D D^T - W W^T to a covariance instead
    (in the skin's modes, or in the q coefficients) keeps much of the noise: a known-law test stated 1.7 x the
    actual variance that way, 1.4 x so (the floor's share), and 1.8 x with the rows as measured.
    """
    variance, correlation = node_variance(errors, valid.size)
    weight = (variance * correlation)[valid]
    scale, bias = split_level(scale, errors, float(variance[valid].mean()))
    model2 = float(model_mm) ** 2 + bias
    if np.ptp(weight) <= 1e-12 * weight.max():
        covariance = inverse * (scale * float(weight[0]) + model2)
    else:
        gain = inverse @ design[valid].T
        covariance = scale * (gain * weight) @ gain.T + model2 * inverse
    if registration is not None:
        moved = inverse @ (design[valid].T @ registration[valid])
        covariance = covariance + moved @ moved.T
    if discrepancy is not None:
        seen, noise = (inverse @ (design[valid].T @ modes[valid]) for modes in discrepancy)
        measured = np.sum(seen**2, axis=1)
        netted = np.clip(measured - np.sum(noise**2, axis=1), 0.0, None)
        share = np.sqrt(netted / np.where(measured > 0, measured, 1.0))
        covariance = covariance + (share[:, None] * seen) @ (share[:, None] * seen).T
    return 0.5 * (covariance + covariance.T)


def estimate_pca(
    basis: PCABasis, field: DisplacementField, min_coverage: float = DEFAULT_MIN_COVERAGE,
    test: ResidualTest | None = None,
) -> ParameterEstimate:
    """The paper's estimator: fit the field with the PCA basis (eq. 4) and combine the states alike (eq. 5).

    field: N normal displacements (mm), NaN where unseen. Returns values = mean_state + c @ component_states (P,),
    their full covariance from the field's error model and the basis' training residual (:func:`parameter_covariance`,
    level checked against the residual), reconstruction (N,) = mean_field + c @ components, and the within-model test
    (``test``: the skin's one test; None: the level test only, see :func:`judge`).
    A unilateral boundary is reported lifted when its reaction, carried through the same combination, is about zero.
    """
    n_nodes = basis.components_.shape[1]
    values, valid = check_field(field, basis.model_id_, n_nodes, min_coverage)
    centred = np.where(valid, values - basis.mean_field_, 0.0)
    normal = valid_normal_matrix(basis.components_, basis.gram_, valid)
    coeff, inverse = solve_normal(normal, basis.components_ @ centred, "PCA pre-factors")
    reconstruction = basis.mean_field_ + coeff @ basis.components_
    residual, rms, worst = residual_stats(values, reconstruction, valid)

    n_valid = int(valid.sum())
    errors = field.errors
    design = basis.components_.T
    model_mm = basis.training_residual_rms_
    check, registration, discrepancy = judge(residual, design, errors, test, model_mm)
    states = basis.component_states_
    coeff_cov = parameter_covariance(design, inverse, valid, errors, check.noise_scale, model_mm, registration,
                                     discrepancy)
    covariance = states.T @ coeff_cov @ states

    n_bilateral = basis.n_bilateral_
    reaction = basis.mean_reaction_ + coeff @ basis.component_reactions_
    lifted = np.zeros(len(basis.names_), dtype=bool)
    lifted[n_bilateral:] = reaction <= LIFTED_REACTION_FRACTION * basis.reaction_scale_
    return ParameterEstimate(
        model_id=basis.model_id_,
        names=basis.names_,
        values=basis.mean_state_ + coeff @ states,
        std=np.sqrt(np.clip(np.diag(covariance), 0.0, None)),
        lower=basis.lower_.copy(),
        upper=basis.upper_.copy(),
        lifted=lifted,
        reconstruction=reconstruction,
        residual=residual,
        residual_rms=rms,
        residual_max=worst,
        coverage=n_valid / n_nodes,
        within_model=check.within_model,
        method="pca",
        covariance=covariance,
        check=check,
    )
