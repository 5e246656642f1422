"""Parameter estimation with the PCA basis (paper eqs. 4-5), and the field checks and weighting every estimator
shares.

The least-squares fit uses the valid (finite) nodes only: an unseen node is missing data, not a zero displacement.
The normal matrix over the valid nodes is the full-field Gram matrix minus the unseen nodes' part, so a fit costs
O(K N) for the right-hand side and O(K^2 N_unseen) for the correction instead of O(K^2 N).

A field that carries an error model is fitted by generalised least squares (:class:`NodeWeight`): weighted by the
inverse of its node covariance diag(d) + U U^T (node noise with its correlation sum, the smoothing bias and the basis'
own error on the diagonal; the registration's rigid-body modes as the low-rank U), applied by Woodbury, never as an
N x N matrix; a calibrated model's discrepancy modes are stated in the covariance, not weighed (:func:`fit_weight`).
The registration error of a scan is nearly a rigid turn of the part, which a hinge or a lock move also nearly is: an
ordinary fit takes it into those parameters (93-99.9 % of their variance on harness (i), benchmarks/RESULTS.md issue
15 run 9); the weighted fit lets the surface's non-rigid shape tell the two apart. A field without an error model (a
simulated one) keeps the ordinary fit, and so does one whose weight is a multiple of the identity (white uniform
noise, no registration), for which both are the same.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from hood_decomp.core.method.pca import PCABasis
from hood_decomp.core.method.residual import (
    ResidualTest,
    check_residual,
    node_variance,
    seen_weights,
    split_level,
    uniform,
    weighted_gram,
)
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
    valid = np.isfinite(values)
    n_valid = int(np.count_nonzero(valid))
    # an inf is not finite: a field seen everywhere has none (no pass for it)
    if n_valid < n_nodes and np.any(np.isinf(values)):
        raise FieldError(f"field holds {int(np.isinf(values).sum())} inf values; unseen nodes must be NaN")
    field.errors.validate(n_nodes)
    if n_valid == 0:
        raise FieldError("field has no finite value (all NaN)")
    coverage = n_valid / n_nodes
    if coverage < min_coverage:
        raise FieldError(f"field coverage {coverage:.3f} is below the minimum {min_coverage:.3f}")
    return values, valid


#: the displacement components an estimate may fit: the normal one (scans measure normal distances; the default)
#: or all three stacked (a simulated or FE field, paper section 3.2: :func:`stacked_field`)
COMPONENTS = ("normal", "xyz")


def stacked_field(field: DisplacementField, normals: np.ndarray, min_coverage: float = DEFAULT_MIN_COVERAGE
                  ) -> DisplacementField:
    """``field``'s three displacement components as the values a ``components="xyz"`` fit reads, (3 N,) mm node by
    node x, y, z (NaN where unseen), in ``normal_displacement`` of the field returned: fitted on the stacked fields of
    the model (:meth:`PCABasis.stacked`, :func:`~.contact_estimation.stacked_model`) by the same estimators.

    normals: (N, 3) the skin's unit normals. Only a field without an error model (kind "none": a simulated or FE
    field): a scan's or a user's stated error model is of the normal values alone, and nothing states the in-plane
    components' errors. Raises FieldError for a field :func:`check_field` refuses (on the skin's N nodes, model id
    not checked: the estimator checks it), one with an error model, without a 3D displacement or whose 3D
    displacement is not the same field (:meth:`DisplacementField.checked_displacement`)."""
    if field.errors.kind != "none":
        raise FieldError(f"components 'xyz' fits a field without an error model (a simulated or FE field); this "
                         f"field's {field.errors.kind!r} error model states the errors of its normal values only")
    check_field(field, field.model_id, np.shape(normals)[0], min_coverage)
    vectors = field.checked_displacement(normals)
    return DisplacementField(field.model_id, vectors.reshape(-1), field.coverage, field.noise_rms)


def valid_normal_matrix(fields: np.ndarray, gram: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Normal matrix over the valid nodes: fields (K, N), gram (K, K) = fields @ fields.T, valid (N,) -> (K, K)."""
    n_unseen = valid.size - int(np.count_nonzero(valid))
    if n_unseen == 0:
        return gram
    if n_unseen < valid.size // 2:
        # by index: a take of the columns is half the CPU of a boolean mask's (a paper scan's 5 % unseen: 0.95 ms)
        part = np.take(fields, np.flatnonzero(~valid), axis=1)
        return gram - part @ part.T
    part = fields[:, valid]
    return part @ part.T


@dataclass(frozen=True)
class NodeWeight:
    """The weight W of a generalised least-squares fit over a field's seen nodes, applied by Woodbury, never as an
    N x N matrix: W = unit x (diag(d_w) + U_w U_w^T)^-1, i.e. W x = w x - diag(w) U_w core U_w^T diag(w) x with
    w = unit / d_w (N,) (0 on unseen nodes), U_w the first ``weighed`` of the ``modes`` U (N, k) (any value on unseen
    nodes: their weight is 0) and core = (unit I + U_w^T diag(w) U_w)^-1 (k_w, k_w). ``unit`` (mm^2) keeps the
    weighted normal matrix in the ordinary one's units (y^T W y / unit is a Mahalanobis energy).
    The node covariance the estimate states is Sigma = diag(d) + U U^T over the seen nodes (d = unit / w); the
    covariance of the fit is :meth:`WeightedSpan.covariance`, unit x (X^T W X)^-1 = (X^T Sigma^-1 X)^-1 when every
    mode is weighed. Made by :func:`node_weight`."""

    weight: np.ndarray
    modes: np.ndarray
    weighed: int
    unit: float

    @cached_property
    def core(self) -> np.ndarray:
        """(k_w, k_w) core of the Woodbury form; :meth:`span` takes it from its Gram (no pass of its own)."""
        return self._core(weighted_gram(np.sqrt(self.weight), self.modes[:, :self.weighed]))

    def _core(self, gram: np.ndarray) -> np.ndarray:
        """core from U_w^T diag(w) U_w (k_w, k_w)."""
        inner = self.unit * np.eye(self.weighed) + gram
        return np.linalg.inv(0.5 * (inner + inner.T))

    def apply(self, x: np.ndarray) -> np.ndarray:
        """W x for x (N,) or (N, m), finite (its unseen entries do not matter: their weight is 0)."""
        wx = self.weight * x if x.ndim == 1 else self.weight[:, None] * x
        used = self.modes[:, :self.weighed]
        back = used @ (self.core @ (used.T @ wx))
        return wx - (self.weight * back if x.ndim == 1 else self.weight[:, None] * back)

    def project(self, fields: np.ndarray, x: np.ndarray) -> np.ndarray:
        """fields (m, N) @ W x, (m,) for x (N,) or (m, j) for x (N, j), finite: the weighted right-hand side (W x
        first: one pass over the fields instead of forming fields W)."""
        return fields @ self.apply(x)

    def span(self, fields: np.ndarray, discrepancy: tuple[np.ndarray, np.ndarray] | None = None,
             field: np.ndarray | None = None) -> WeightedSpan:
        """The fields (m, N) of a fit (finite on every node) under this weight, with the field's low-rank errors, a
        calibrated model's discrepancy pair (D, E) (None: none) and the field y (N,) mm fitted (finite; None: none):
        their one weighted Gram (:class:`WeightedSpan`)."""
        parts = (fields.T, self.modes, *(discrepancy or ()), *(() if field is None else (field[:, None],)))
        gram = weighted_gram(np.sqrt(self.weight), *parts)
        m, kw = fields.shape[0], self.weighed
        if "core" not in self.__dict__:  # the cached core, from this Gram's U_w block
            self.__dict__["core"] = self._core(gram[m:m + kw, m:m + kw])
        return WeightedSpan(self, gram, m, 0 if discrepancy is None else discrepancy[0].shape[1], field is not None)


@dataclass(frozen=True)
class WeightedSpan:
    """A fit's fields F (m, N) under a field's weight W (:class:`NodeWeight`): the Gram C^T diag(w) C of C = [F^T, U,
    D, E] over the seen nodes (U the field's low-rank errors, the first k_w of them weighed; (D, E) a calibrated
    model's discrepancy as measured and its rows' noise, absent: ``n_discrepancy`` 0; then the fitted field y when
    ``has_field``), formed once by one syrk. The weighted normal matrix, the right-hand side, the field's energy and
    the covariance of any fit on X = F^T L follow from it without another pass over the nodes. Made by
    :meth:`NodeWeight.span`."""

    weight: NodeWeight
    gram: np.ndarray
    n_fields: int
    n_discrepancy: int
    has_field: bool = False

    def normal(self) -> np.ndarray:
        """F W F^T (m, m): the weighted normal matrix, W = diag(w) - diag(w) U_w core U_w^T diag(w)
        (:class:`NodeWeight`)."""
        m, kw = self.n_fields, self.weight.weighed
        moved = self.gram[:m, m:m + kw]
        return self.gram[:m, :m] - moved @ self.weight.core @ moved.T

    def rhs(self) -> np.ndarray:
        """F W y (m,): the weighted right-hand side of the field the span holds (:meth:`NodeWeight.project`)."""
        assert self.has_field, "a span made without the field has no right-hand side"
        m, kw = self.n_fields, self.weight.weighed
        return self.gram[:m, -1] - self.gram[:m, m:m + kw] @ (self.weight.core @ self.gram[m:m + kw, -1])

    def energy(self) -> float:
        """y^T W y of the field the span holds."""
        assert self.has_field, "a span made without the field has no energy"
        m, kw = self.n_fields, self.weight.weighed
        moved = self.gram[m:m + kw, -1]
        return float(self.gram[-1, -1] - moved @ self.weight.core @ moved)

    def covariance(self, lift: np.ndarray, inverse: np.ndarray) -> np.ndarray:
        """(q, q) covariance of theta = inverse X^T W y for the design X = F^T lift (lift (m, q)), inverse = (X^T W
        X)^-1: the sandwich G Sigma G^T with G = inverse X^T W (the GLS covariance when the weight is Sigma's own
        inverse), plus the discrepancy (D, E) netted along G (:func:`discrepancy_along_gains`) when the span has it.

        With M = core (X^T w U_w)^T the gain is G^T = W X = diag(w) Y, Y = X - U_w M, and w d = unit on the seen
        nodes, so X^T W diag(d) W X = unit Y^T diag(w) Y, and W X's product with a mode u is Y^T diag(w) u."""
        m, kw, k = self.n_fields, self.weight.weighed, self.weight.modes.shape[1]
        end = self.gram.shape[0] - self.has_field
        rows = lift.T @ self.gram[:m, :end]  # X^T diag(w) C (q, m + k + ...)
        xx, xw = rows[:, :m] @ lift, rows[:, m:m + kw]
        shift = self.weight.core @ xw.T
        along = rows[:, m:] - shift.T @ self.gram[m:m + kw, m:end]  # Y^T diag(w) [U, D, E]
        ww = self.gram[m:m + kw, m:m + kw]
        spread = xx - xw @ shift - shift.T @ xw.T + shift.T @ ww @ shift  # Y^T diag(w) Y
        moved = along[:, :k]
        covariance = inverse @ (self.weight.unit * spread + moved @ moved.T) @ inverse
        if self.n_discrepancy:
            d = self.n_discrepancy
            covariance = covariance + discrepancy_along_gains(inverse @ along[:, k:k + d], inverse @ along[:, k + d:])
        return 0.5 * (covariance + covariance.T)


def node_weight(
    errors: FieldErrorModel, valid: np.ndarray, level: float, model_mm: float, modes: np.ndarray | None,
    unit: float = 1.0, weighed: int | None = None,
) -> NodeWeight | None:
    """The weight of a generalised least-squares fit (:class:`NodeWeight`), or None where the ordinary fit is the same
    or nothing states the covariance: a field without an error model, or a diagonal that is uniform over the seen
    nodes without weighed low-rank errors.

    valid: (N,) seen nodes. level: the residual-supported level of the within-model test (ModelCheck.noise_scale),
    split into node noise and smoothing bias by :func:`~.residual.split_level`; model_mm: the basis' own white error.
    modes: (N, k) mm the low-rank field errors (registration, model discrepancy: :meth:`ResidualTest.error_modes`;
    finite, any value on unseen nodes), None for none; the first ``weighed`` of them (None: all) enter the weight,
    all of them the stated covariance.
    Sigma = noise diag(v g) + (model^2 + bias) I + U U^T is the node covariance :func:`parameter_covariance` states
    for an ordinary fit, so the weighted fit's covariance is that same model's.
    """
    if errors.kind == "none":
        return None
    variance, correlation = node_variance(errors, valid.size)
    noise, bias = split_level(level, errors, float(variance[valid].mean()))
    diagonal = noise * (variance * correlation)[valid] + float(model_mm) ** 2 + bias
    modes = np.zeros((valid.size, 0)) if modes is None else modes
    used = modes[:, :weighed]
    if used.shape[1] == 0 and uniform(diagonal):
        return None
    weight = np.zeros(valid.size)
    weight[valid] = unit / diagonal
    return NodeWeight(weight, modes, used.shape[1], float(unit))


def weighted_normal(fields: np.ndarray, gram: np.ndarray, valid: np.ndarray, span: WeightedSpan | None) -> np.ndarray:
    """fields W fields^T (m, m) over the seen nodes: fields (m, N), gram (m, m) = fields @ fields.T; W the field's
    weight (``span``: the fields under it, :meth:`NodeWeight.span`), the identity for an ordinary fit (None:
    :func:`valid_normal_matrix`)."""
    return valid_normal_matrix(fields, gram, valid) if span is None else span.normal()


def weighted_rhs(fields: np.ndarray, x: np.ndarray, valid: np.ndarray, weight: NodeWeight | None) -> np.ndarray:
    """fields (m, N) @ W x over the seen nodes, (m,) for x (N,) or (m, j) for x (N, j): W the field's weight, the
    identity for an ordinary fit (None)."""
    if not valid.all():
        x = np.where(valid if x.ndim == 1 else valid[:, None], x, 0.0)
    return fields @ x if weight is None else weight.project(fields, x)


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
    residual = values - reconstruction
    if valid.all():  # no copy of the seen values (values are finite where valid)
        seen = residual
    else:
        residual[~valid] = np.nan
        seen = residual[valid]
    # max |r| as the larger of max r and -min r: two reductions, no |r| array
    return residual, float(np.sqrt(np.dot(seen, seen) / seen.size)), float(max(seen.max(), -seen.min()))


def judge(
    residual: np.ndarray, design: np.ndarray | None, errors: FieldErrorModel, test: ResidualTest | None,
    model_mm: float, span: np.ndarray | None = None, local: bool = True, span_r: np.ndarray | None = None,
) -> tuple[ModelCheck, np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
    """The within-model test of a fit on ``design`` (N, p) (``test``'s when given, else the level test without
    smooth modes) and the low-rank field errors (N, k) the covariance adds (the field's registration modes and the
    calibrated model's discrepancy modes, :meth:`ResidualTest.error_modes`; None without either). span: (N, q) all the
    fields the model can make, whose directions the smooth test leaves out (default: the design). local: False
    leaves the test's one-ring part out (:meth:`ResidualTest.check`). span_r: (q,) span^T residual over the seen nodes
    when the fit has it (an ordinary fit: its right-hand side less its normal matrix times its coefficients), which
    spares the test a pass over the nodes; None: formed by the test.

    Without a ``test`` the estimator has no skin, so a registration covariance cannot reach the nodes and is left
    out (the covariance is then that of the field given its registration); the verbs and nodes always estimate
    through the bases (estimate_field), which pass the skin's test. Close-loop's tracing estimates are made so.
    Third: the discrepancy as measured and its rows' noise, (D, W) (:meth:`ResidualTest.discrepancy_pair`), which
    the covariance nets along its gains; None when the bases state no noise (D is then among the error modes)."""
    if test is None:
        return check_residual(residual, design, errors, model_mm=model_mm), None, None
    registration = test.registration(errors)
    return (test.check(residual, design if span is None else span, errors, model_mm, registration, local, span_r),
            test.error_modes(errors, registration), test.discrepancy_pair())


def fit_weight(
    centred: np.ndarray, valid: np.ndarray, span: np.ndarray, errors: FieldErrorModel, test: ResidualTest | None,
    model_mm: float, unit: float = 1.0,
) -> tuple[WeightedSpan | None, ModelCheck | None, np.ndarray | None]:
    """The weight of an estimator's fit (:func:`node_weight`) over the fields it fits (``span``.T, with the test's
    discrepancy pair and the field ``centred``: :meth:`NodeWeight.span`) from the field before the fit, with the
    within-model test and the low-rank field errors it used: centred (N,) mm the field minus the model's offset
    (finite; any value where unseen), valid (N,) the seen nodes; span (N, q) every field the model can make (the
    estimator's fields, transposed: what it fits). The test projects the span out, so its level (and, unless it
    looks at the fit's own residual, :meth:`ResidualTest.looks_at_fit`, its whole verdict) is the same for the field as
    for any fit's residual: it is made here, once, and returned (None: the estimator judges its residual itself). (None,
    None, None) without a test or an error model: with no skin no registration reaches the nodes (:func:`judge`), and
    the level test without smooth modes needs the ordinary fit's residual."""
    if test is None or errors.kind == "none":
        return None, None, None
    if not errors.has_pose and seen_weights(errors, valid)[0] is not None:
        return None, None, None  # the weight a multiple of I whatever the level: the ordinary fit
    # no one-ring part: where a field takes it (looks_at_fit), the fit's own residual is judged and this verdict
    # dropped; only its level is used (at paper resolution the part's projection was 90-180 ms of a posed field)
    check, modes, pair = judge(np.where(valid, centred, np.nan), span, errors, test, model_mm, local=False)
    # the registration is weighed (the first of the error modes), a calibrated model's discrepancy and its
    # calibration's own error only stated: they are estimated from a handful of calibration entries, and a fit that
    # leans away from their span leans on what the estimate missed (on 40 CalculiX parts of the coarse hood 68 % of
    # the errors inside the stated 95 % interval instead of >= 90 %)
    stated = sum(m.shape[1] for m in test.stated_modes())
    weight = node_weight(errors, valid, check.noise_scale, model_mm, modes, unit,
                         0 if modes is None else modes.shape[1] - stated)
    weighted = None if weight is None else weight.span(span.T, pair, centred)
    return weighted, None if test.looks_at_fit(errors) else check, modes


def parameter_covariance(
    design: np.ndarray | None, inverse: np.ndarray, valid: np.ndarray, errors: FieldErrorModel, scale: float,
    model_mm: float, registration: np.ndarray | None,
    discrepancy: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Covariance (q, q) of least-squares coefficients theta = inverse @ design[valid].T @ y (design (N, q); None where
    :func:`covariance_reads_design` says it is not read).

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
    variance = node_variance(errors, valid.size)[0]
    # the seen nodes' mean variance only splits a level with a bias term (a pass over the nodes otherwise spent)
    mean_variance = float(variance[valid].mean()) if errors.bias_correlation > 0 else 0.0
    scale, bias = split_level(scale, errors, mean_variance)
    model2 = float(model_mm) ** 2 + bias
    flat, weight = seen_weights(errors, valid)
    if flat is not None:
        covariance = inverse * (scale * flat + model2)
    else:
        gain = inverse @ design[valid].T
        covariance = scale * (gain * weight) @ gain.T + model2 * inverse
    if registration is not None:
        moved = inverse @ (design[valid].T @ registration[valid])
        covariance = covariance + moved @ moved.T
    if discrepancy is not None:
        gains = (inverse @ (design[valid].T @ m[valid]) for m in discrepancy)
        covariance = covariance + discrepancy_along_gains(*gains)
    return 0.5 * (covariance + covariance.T)


def covariance_reads_design(errors: FieldErrorModel, valid: np.ndarray, registration: np.ndarray | None,
                            discrepancy: tuple[np.ndarray, np.ndarray] | None) -> bool:
    """Whether :func:`parameter_covariance` reads its design for a field with ``errors`` seen on ``valid`` (N,) bool:
    not for a weight uniform there (:func:`seen_weights`; a field that states none too) without a registration or a
    discrepancy, whose covariance is the normal matrix' inverse times one level. A caller that forms its design for
    the covariance alone (the contact-aware estimator's F^T lift, (N, n_theta): ~30 MB and a product over all nodes at
    paper resolution) can skip it then."""
    return registration is not None or discrepancy is not None or seen_weights(errors, valid)[0] is None


def discrepancy_along_gains(seen: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(q, q) the calibrated model's discrepancy along an estimate's gains G (q, N) (:func:`parameter_covariance`):
    seen = G D (q, k) the discrepancy rows as measured, noise = G W (q, K) their expected noise. Per coefficient
    g^T (D D^T - W W^T) g, floored at 0, with the rows as measured scaled to it."""
    measured = np.sum(seen**2, axis=1)
    netted = np.clip(measured - np.sum(noise**2, axis=1), 0.0, None)
    scaled = np.sqrt(netted / np.where(measured > 0, measured, 1.0))[:, None] * seen
    return scaled @ scaled.T


def estimate_pca(
    basis: PCABasis, field: DisplacementField, min_coverage: float = DEFAULT_MIN_COVERAGE,
    test: ResidualTest | None = None,
) -> ParameterEstimate:
    """The paper's estimator: fit the field with the PCA basis (eq. 4) and combine the states alike (eq. 5); a field
    with an error model is fitted by generalised least squares (module docstring, :func:`fit_weight`).

    field: N normal displacements (mm), NaN where unseen. Returns values = mean_state + c @ component_states (P,),
    their full covariance from the field's error model and the basis' training residual (:func:`parameter_covariance`,
    level checked against the residual), reconstruction (N,) = mean_field + c @ components, and the within-model test
    (``test``: the skin's one test; None: the level test only, see :func:`judge`).
    A unilateral boundary is reported lifted when its reaction, carried through the same combination, is about zero.
    The stacked basis, field and test of a three-component fit (:meth:`PCABasis.stacked`, :func:`stacked_field`,
    :meth:`ResidualTest.stacked`) are fitted alike, their 3 N values as the N here.
    """
    n_nodes = basis.components_.shape[1]
    values, valid = check_field(field, basis.model_id_, n_nodes, min_coverage)
    n_valid = int(np.count_nonzero(valid))
    centred = values - basis.mean_field_
    if n_valid < n_nodes:  # unseen nodes count as 0 (a field seen everywhere: no pass for it)
        centred[~valid] = 0.0
    errors = field.errors
    design = basis.components_.T
    model_mm = basis.training_residual_rms_
    span, check, registration = fit_weight(centred, valid, design, errors, test, model_mm)
    weight = None if span is None else span.weight
    discrepancy = None if test is None else test.discrepancy_pair()
    normal = weighted_normal(basis.components_, basis.gram_, valid, span)
    rhs = weighted_rhs(basis.components_, centred, valid, None) if span is None else span.rhs()
    coeff, inverse = solve_normal(normal, rhs, "PCA pre-factors")
    reconstruction = coeff @ basis.components_
    reconstruction += basis.mean_field_  # in place: no second (N,) array
    residual, rms, worst = residual_stats(values, reconstruction, valid)

    if check is None:
        # an ordinary fit's residual projects on its design as rhs - normal c over the seen nodes: no pass
        check, registration, discrepancy = judge(residual, design, errors, test, model_mm,
                                                 span_r=rhs - normal @ coeff if span is None else None)
    states = basis.component_states_
    if span is None:
        coeff_cov = parameter_covariance(design, inverse, valid, errors, check.noise_scale, model_mm, registration,
                                         discrepancy)
    else:
        coeff_cov = span.covariance(np.eye(design.shape[1]), inverse)
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
        weighting="ordinary" if weight is None else "generalised",
    )
