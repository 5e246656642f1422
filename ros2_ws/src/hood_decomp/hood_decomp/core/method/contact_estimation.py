"""Contact-aware parameter estimation with the reduced FE model (beyond the paper).

For a fixed contact state (which pad springs touch), the skin field of :class:`ReducedModel` is affine in the
unknowns theta = (bilateral states a, commanded positions b of the pads in contact):

    active springs C:  f_C = M_C^-1 (E b + preload_C - z0_C - Sa_C a),  M_C = diag(1 / k_C) + H_CC,  f_other = 0
    w = w0 + R a + G f

so each candidate contact state is one small least-squares problem. The solution kept satisfies the contact
conditions (no tension f >= 0, no penetration b + preload - z <= 0 on the free springs of a touching pad) and fits
best. Candidates come from an active-set iteration started from every in-contact/lifted combination of the pads.
A lifted pad leaves no trace in the field: its value is the part's position there, min_k (z_k - preload_k), which
the commanded position does not exceed.

Everything per candidate works in the (B + S)-dimensional space of u = (a, f): the normal matrix of [R G] over the
seen nodes is formed once per field, so a candidate costs O((B + S)^3), not O(N). A field with an error model is
fitted by generalised least squares (:mod:`.estimation`): the normal matrix, right-hand side and energy are the
weighted ones, scaled by the field's noise level (``noise2``) so that noise2 x (normal matrix)^-1 stays the
covariance and rss / noise2 the Mahalanobis energy every contact-state comparison below uses.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from hood_decomp.core.method.estimation import (
    DEFAULT_MIN_COVERAGE,
    NodeWeight,
    WeightedSpan,
    check_field,
    covariance_reads_design,
    fit_weight,
    judge,
    parameter_covariance,
    residual_stats,
    weighted_normal,
    weighted_rhs,
)
from hood_decomp.core.method.model_spread import Factor, SkinChange, factor_effects
from hood_decomp.core.method.residual import ResidualTest, node_variance
from hood_decomp.core.types import (
    DisplacementField,
    FieldErrorModel,
    ModelCheck,
    ParameterEstimate,
    ReducedModel,
    side_by_side,
)
from hood_decomp.errors import FieldError, ModelError

# Start from every pad combination up to this many pads (2^U starts); beyond it, all-touching and all-lifted only.
MAX_ENUMERATED_PADS = 5
# The local search after the active-set iterations tries flipping this many springs closest to changing state.
MAX_FLIPS = 8
# Contact conditions are checked with this slack, relative to the force / gap scale of the candidate ...
CONTACT_RTOL = 1e-9
# ... plus this many standard deviations of the force / gap under the field's stated noise (none when unknown): with
# scan noise the best fit may sit on the boundary between two contact states, where each state's unconstrained
# solution violates its conditions insignificantly.
CONTACT_SIGMAS = 3.0
# A touching pad whose total spring compression (sum f / k) is within LIFTED_SIGMAS of its std carries no load the
# field can show: it is reported lifted, at the part's position (well determined, unlike b). The std is the field's
# (on a noise-free field the fit's round-off), never an absolute floor: a rigid buffer (hood-paper, 7e8 N/mm per
# spring) carrying 60 N is compressed by 1e-7 mm, and a fixed 1e-7 mm floor reported it lifted, its reaction
# absorbed by the bilateral states (HINGE_X 0.09 mm off on a noise-free member of the model).
LIFTED_SIGMAS = 2.0
# On a noisy field (a noise level stated by noise_rms or by the error model) a pad carrying less than this total
# force (N) is reported lifted too: a scan-derived field has a spatially correlated smoothing error that the
# white-noise std above does not see, and on the default hood it makes a lifted pad look touching with 1-2 N (a seated
# pad carries 100-250 N); on white-noise fields a light touch took a lifted pad's correction 6 std off. The commanded
# position of such a pad is not observable; its part position is.
MEASURED_MIN_PAD_FORCE_N = 5.0


def stacked_model(model: ReducedModel) -> ReducedModel:
    """``model`` with its 3D skin responses as the skin fields it fits (a ``components="xyz"`` estimate, paper section
    3.2): w0 (3 N,), R (3 N, B), G (3 N, S) are w0_3d, R_3d, G_3d node by node x, y, z, the values of
    :func:`~.estimation.stacked_field`; the pad springs and the 3D arrays are the model's."""
    n_values = 3 * model.w0_3d.shape[0]
    return replace(model, w0=model.w0_3d.reshape(n_values), R=model.R_3d.reshape(n_values, -1),
                   G=model.G_3d.reshape(n_values, -1))


@dataclass(frozen=True)
class _Candidate:
    active: np.ndarray  # (S,) bool
    theta: np.ndarray  # (B + n_touching,)
    lift: np.ndarray  # (m, n_theta): u = lift @ theta + offset
    offset: np.ndarray  # (m,)
    normal_inverse: np.ndarray  # (n_theta, n_theta)
    rss: float
    feasible: bool


@dataclass(frozen=True)
class _Fit:
    """The reported fit of one contact state (:meth:`ContactEstimator._fit`); unseen: (U,) pads touching in the state
    whose compression the field cannot show."""

    values: np.ndarray
    covariance: np.ndarray
    lifted: np.ndarray
    unseen: np.ndarray
    reconstruction: np.ndarray
    residual: np.ndarray
    rms: float
    worst: float
    check: ModelCheck
    effects: np.ndarray | None  # (F, P) mm: the considered model factors' effects (model_spread); None: none


class ContactEstimator:
    """Estimate parameter states with the contact conditions of the unilateral boundaries.

    Parameters: min_coverage (fraction of skin nodes that must be seen).
    ``fit(model, lower, upper, test=None, pad_shift=None)``: model is the :class:`ReducedModel`; lower, upper (B + U,)
    mm declared ranges; test: the skin's fitted :class:`ResidualTest` (the one within-model test; None: level test
    only); pad_shift: (S,) mm a part of the pad springs' displacement in ``model.z0`` that is no boundary state (a
    warm part's thermal expansion, :meth:`Bases.at_temperature`), taken out of a lifted pad's reported position (the
    part's position there as at the reference temperature); None: none. factors: the model's physical factors
    considered (:func:`~.model_spread.factor_spread`; each estimate reports their effects); (): none.
    Fitted: model_, lower_, upper_, test_, pad_shift_ (S,), factors_, changes_ (per factor the (plus, minus)
    :class:`~.model_spread.SkinChange`), fields_ (B + S, N) = [R G]^T, gram_ (B + S, B + S), touching_pads_.
    """

    def __init__(self, min_coverage: float = DEFAULT_MIN_COVERAGE,
                 measured_min_pad_force_n: float = MEASURED_MIN_PAD_FORCE_N):
        self.min_coverage = min_coverage
        self.measured_min_pad_force_n = measured_min_pad_force_n

    def fit(self, model: ReducedModel, lower: np.ndarray, upper: np.ndarray,
            test: ResidualTest | None = None, pad_shift: np.ndarray | None = None,
            factors: tuple[Factor, ...] = ()) -> ContactEstimator:
        n_params = len(model.names)
        n_pads = n_params - model.n_bilateral
        if np.shape(lower) != (n_params,) or np.shape(upper) != (n_params,):
            raise ModelError(f"lower/upper must have shape ({n_params},), got {np.shape(lower)} and {np.shape(upper)}")
        if model.pad_of.size and (model.pad_of.min() < 0 or model.pad_of.max() >= n_pads):
            raise ModelError(f"pad_of must index the {n_pads} unilateral parameters, got {model.pad_of}")
        self.model_ = model
        self.test_ = test
        self.factors_ = tuple(factors)
        self.changes_ = tuple((SkinChange.between(model, factor.plus), SkinChange.between(model, factor.minus))
                              for factor in self.factors_)
        self.pad_shift_ = np.zeros(model.k.size) if pad_shift is None else np.asarray(pad_shift, dtype=float)
        if self.pad_shift_.shape != model.k.shape:
            raise ModelError(f"pad_shift must have shape {model.k.shape}, got {self.pad_shift_.shape}")
        self.lower_ = np.asarray(lower, dtype=float)
        self.upper_ = np.asarray(upper, dtype=float)
        # row by row in memory whatever the model's arrays' order (a loaded file's are row-major, and np.vstack of
        # their transposes is then column-major): the weighted Grams read the fields transposed, column by column
        self.fields_ = side_by_side(model.R, model.G).T
        self.gram_ = self.fields_ @ self.fields_.T
        if n_pads <= MAX_ENUMERATED_PADS:
            starts = list(itertools.product((True, False), repeat=n_pads))
        else:
            starts = [(True,) * n_pads, (False,) * n_pads]
        self.touching_pads_ = np.array(starts, dtype=bool).reshape(len(starts), n_pads)
        return self

    def _solve(self, active: np.ndarray, normal: np.ndarray, rhs: np.ndarray, total: float) -> _Candidate:
        """Least squares for one contact state; normal = [R G]^T[R G], rhs = [R G]^T y over seen nodes."""
        model = self.model_
        n_b = model.n_bilateral
        n_s = active.size
        pads = np.unique(model.pad_of[active])
        idx = np.flatnonzero(active)
        n_theta = n_b + pads.size
        lift = np.zeros((n_b + n_s, n_theta))
        offset = np.zeros(n_b + n_s)
        lift[:n_b, :n_b] = np.eye(n_b)
        if idx.size:
            compliance = np.diag(1.0 / model.k[idx]) + model.H[np.ix_(idx, idx)]
            inv = np.linalg.inv(compliance)
            select = (model.pad_of[idx][:, None] == pads[None, :]).astype(float)
            lift[n_b + idx, :n_b] = -inv @ model.Sa[idx]
            lift[n_b + idx, n_b:] = inv @ select
            offset[n_b + idx] = inv @ (model.preload[idx] - model.z0[idx])
        reduced = lift.T @ normal @ lift
        eigval, eigvec = np.linalg.eigh(reduced)
        if eigval[0] <= 1e-12 * max(eigval[-1], 1e-300):
            return _Candidate(active, np.zeros(n_theta), lift, offset, np.zeros((n_theta, n_theta)), np.inf, False)
        normal_inverse = (eigvec / eigval) @ eigvec.T
        theta = normal_inverse @ (lift.T @ (rhs - normal @ offset))
        u = lift @ theta + offset
        rss = max(float(u @ normal @ u - 2.0 * u @ rhs + total), 0.0)
        return _Candidate(active, theta, lift, offset, normal_inverse, rss, True)

    def _violations(self, cand: _Candidate, noise2: float) -> tuple[np.ndarray, np.ndarray]:
        """(tension (S,) bool on active springs, penetration (S,) bool on free springs of touching pads)."""
        model = self.model_
        n_b = model.n_bilateral
        u = cand.lift @ cand.theta + cand.offset
        a, f = u[:n_b], u[n_b:]
        z = model.z0 + model.Sa @ a + model.H @ f
        pads = np.unique(model.pad_of[cand.active])
        b = np.full(self.touching_pads_.shape[1], np.nan)
        b[pads] = cand.theta[n_b:]
        pen = b[model.pad_of] + model.preload - z
        # Standard deviations of f and of the gap from the covariance noise^2 * normal_inverse.
        cov = noise2 * cand.normal_inverse
        df = cand.lift[n_b:]
        dz = model.Sa @ cand.lift[:n_b] + model.H @ df
        dpen = -dz
        if pads.size:
            dpen[:, n_b:] += (model.pad_of[:, None] == pads[None, :]).astype(float)
        f_std = np.sqrt(np.clip(np.einsum("st,tu,su->s", df, cov, df), 0.0, None))
        pen_std = np.sqrt(np.clip(np.einsum("st,tu,su->s", dpen, cov, dpen), 0.0, None))
        f_tol = CONTACT_RTOL * (1.0 + np.abs(f).max(initial=0.0)) + CONTACT_SIGMAS * f_std
        pen_tol = CONTACT_RTOL * (1.0 + np.abs(z).max(initial=0.0)) + CONTACT_SIGMAS * pen_std
        tension = cand.active & (f < -f_tol)
        touching = np.isin(model.pad_of, pads)
        penetration = ~cand.active & touching & (pen > pen_tol)
        return tension, penetration

    def _evaluate(self, active: np.ndarray, problem: tuple, cache: dict) -> tuple[_Candidate, np.ndarray, np.ndarray]:
        """Solve one contact state and check its conditions, once per field (the searches revisit states often).
        problem = (normal, rhs, total, noise2)."""
        key = active.tobytes()
        if key not in cache:
            normal, rhs, total, noise2 = problem
            cand = self._solve(active, normal, rhs, total)
            none = np.zeros(active.size, dtype=bool)
            cache[key] = (cand, *self._violations(cand, noise2)) if cand.feasible else (cand, none, none)
        return cache[key]

    def _active_set(self, start: np.ndarray, problem: tuple, cache: dict) -> _Candidate | None:
        """Active-set iteration from ``start`` (S,) bool: drop springs in tension, add penetrating ones."""
        active = start.copy()
        seen: set[bytes] = set()
        for _ in range(4 * active.size + 8):
            key = active.tobytes()
            if key in seen:
                return None
            seen.add(key)
            cand, tension, penetration = self._evaluate(active, problem, cache)
            if not cand.feasible:
                return None
            if not tension.any() and not penetration.any():
                return cand
            active = (active & ~tension) | penetration
        return None

    def estimate(self, field: DisplacementField) -> ParameterEstimate:
        """Estimate (a, b) of one field (N,) mm, NaN where unseen; see the module docstring. An estimator fitted on
        a :func:`stacked_model` estimates a :func:`~.estimation.stacked_field` alike, its 3 N values as the N here."""
        model = self.model_
        n_nodes = model.w0.shape[0]
        values, valid = check_field(field, model.model_id, n_nodes, self.min_coverage)
        y = np.where(valid, values - model.w0, 0.0)
        n_valid = int(valid.sum())
        errors = field.errors
        variance = node_variance(errors, n_nodes)[0]
        # the contact conditions' noise slack: the field's noise, else the level its error model states (without
        # it, a field that states its noise only through the error model had its contact state forced by noise:
        # errors of 7-9 std on 2 of 2,000 noise-only fields of the default hood)
        if np.isfinite(field.noise_rms):
            noise2 = float(field.noise_rms) ** 2
        else:
            noise2 = float(variance[valid].mean()) if errors.kind != "none" else 0.0
        span, check, modes = (None, None, None) if noise2 <= 0 else fit_weight(
            y, valid, self.fields_.T, errors, self.test_, 0.0, unit=noise2)
        weight = None if span is None else span.weight
        normal = weighted_normal(self.fields_, self.gram_, valid, span)
        total = float(y @ y) if span is None else span.energy()
        rhs = weighted_rhs(self.fields_, y, valid, None) if span is None else span.rhs()
        problem, cache = (normal, rhs, total, noise2), {}
        candidates: dict[bytes, _Candidate] = {}
        for touching in self.touching_pads_:
            start = touching[model.pad_of]
            cand = self._active_set(start, problem, cache)
            if cand is not None:
                candidates.setdefault(cand.active.tobytes(), cand)
        if not candidates:
            raise FieldError("no contact state satisfies the contact conditions for this field")
        self._improve(candidates, problem, cache)
        best = self._select(list(candidates.values()), n_valid)
        measured = noise2 > 0  # a noisy field: its noise level stated by noise_rms or by its error model
        min_force = self.measured_min_pad_force_n if measured else 0.0
        fit = self._fit(best, values, valid, errors, min_force, normal, span, check, modes)
        if fit.unseen.any() and not measured:
            # Without a noise level nothing weighs the contact states (no spread term): a touch the field cannot show
            # (compression within LIFTED_SIGMAS of its std, the model's discrepancy included) is decided lifted, and
            # its position and the other values come from the fit without it: the touching fit's light force only
            # absorbs model error (on a calibrated model 5 K warmer, a 1 N touch of a lifted buffer moved its
            # reported position 0.011 mm). On a noisy field the spread to the other states covers it (reporting the
            # lifted fit there overstated the buffers' std: median |z| 0.40 on the coarse hood's validation).
            free = np.isin(model.pad_of, np.flatnonzero(fit.unseen))
            cand, tension, penetration = self._evaluate(best.active & ~free, problem, cache)
            if cand.feasible and not tension.any() and not penetration.any():
                best = candidates.setdefault(cand.active.tobytes(), cand)
                fit = self._fit(best, values, valid, errors, min_force, normal, span, check, modes)
        covariance = fit.covariance + self._between_states(candidates.values(), best, fit.values, noise2, min_force,
                                                             n_valid)
        return ParameterEstimate(
            model_id=model.model_id,
            names=tuple(model.names),
            values=fit.values,
            std=np.sqrt(np.clip(np.diag(covariance), 0.0, None)),
            lower=self.lower_.copy(),
            upper=self.upper_.copy(),
            lifted=fit.lifted,
            reconstruction=fit.reconstruction,
            residual=fit.residual,
            residual_rms=fit.rms,
            residual_max=fit.worst,
            coverage=n_valid / n_nodes,
            within_model=fit.check.within_model,
            method="contact",
            covariance=covariance,
            check=fit.check,
            model_factors=tuple(factor.name for factor in self.factors_),
            model_effects=fit.effects,
            weighting="ordinary" if weight is None else "generalised",
        )

    def _fit(self, best: _Candidate, values: np.ndarray, valid: np.ndarray, errors: FieldErrorModel,
             min_force_n: float, normal: np.ndarray, span: WeightedSpan | None, check: ModelCheck | None,
             registration: np.ndarray | None) -> _Fit:
        """The reported fit of a contact state: refined theta, residual, within-model test and values; normal: the
        fields' (weighted) normal matrix over the seen nodes; span: the field's generalised least-squares weight over
        the fields (None: the ordinary fit); check: the field's
        within-model test made before the fit (:func:`~.estimation.fit_weight`) and its low-rank field errors, None:
        judged here on the fit's residual."""
        model = self.model_
        weight = None if span is None else span.weight
        # One step of iterative refinement on the real residual: the normal equations square the condition number.
        first = best.lift @ best.theta + best.offset
        reconstruction = model.w0 + first @ self.fields_
        projected = weighted_rhs(self.fields_, values - reconstruction, valid, weight)  # F W r over the seen nodes
        theta = best.theta + best.normal_inverse @ (best.lift.T @ projected)
        u = best.lift @ theta + best.offset
        reconstruction = model.w0 + u @ self.fields_
        residual, rms, worst = residual_stats(values, reconstruction, valid)
        # theta is linear least squares on the design F^T lift (N, n_theta) for the chosen contact state; the test
        # watches smooth fields outside everything the model can make (any pad force pattern, [R G]): the scan
        # step's bias is largest at the pads' kinks
        discrepancy = None if self.test_ is None else self.test_.discrepancy_pair()
        # the ordinary fit's design F^T lift (N, n_theta), made where it is read (the weighted fit needs only its lift;
        # a test on the skin judges the span, not the design; a white field's covariance does not read it)
        def design() -> np.ndarray:
            return self.fields_.T @ best.lift

        if check is None:  # the ordinary fit's residual on the span, F r - normal (u - first): no pass for the test
            check, registration, discrepancy = judge(residual, design() if self.test_ is None else None, errors,
                                                     self.test_, 0.0, span=self.fields_.T,
                                                     span_r=projected - normal @ (u - first) if span is None else None)
        if span is None:
            reads = covariance_reads_design(errors, valid, registration, discrepancy)
            theta_cov = parameter_covariance(design() if reads else None, best.normal_inverse, valid, errors,
                                             check.noise_scale, 0.0,
                                             registration, discrepancy)
        else:
            theta_cov = span.covariance(best.lift, best.normal_inverse)
        out_values, covariance, lifted, unseen = self._report(best, theta, theta_cov, min_force_n)
        effects = None
        if self.factors_:
            effects, read = self._factor_effects(best, theta, valid, theta_cov, min_force_n, normal, weight)
            # A calibration's uncertainty of its fitted factors belongs to the stated covariance (its skin part is the
            # bases' calibration_noise); the part no field shows, a lifted pad's position read through the calibrated
            # pad springs (z0 + Sa a + H f - preload, which the skin-only correction does not calibrate), is added
            # here and leaves the factor's model effect, so the gate's sqrt(std^2 + model_std^2) counts it once.
            # Without it the truly lifted buffers of the CalculiX stand-in were 82.4 % covered by their std, 97.1 %
            # with it (918 pads, 20 families; benchmarks/RESULTS.md, session 13).
            read = read * np.array([factor.calibrated for factor in self.factors_], float)[:, None]
            covariance = covariance + read.T @ read
            effects = effects - read
        return _Fit(out_values, covariance, lifted, unseen, reconstruction, residual, rms, worst, check, effects)

    def _factor_effects(self, best: _Candidate, theta: np.ndarray, valid: np.ndarray, theta_cov: np.ndarray,
                        min_force_n: float, normal: np.ndarray, weight: NodeWeight | None
                        ) -> tuple[np.ndarray, np.ndarray]:
        """(F, P) mm: the considered factors' effects and their part read through the pad springs
        (:func:`~.model_spread.factor_effects`) through this fit's linear map, in the (B + S) space: a field change
        dw moves rhs by [R G]^T W dw over the seen nodes (the weighted fit leans on non-rigid shape, which the factors
        move too); normal: [R G]^T W [R G] there."""
        def project(x: np.ndarray) -> np.ndarray:
            return weighted_rhs(self.fields_, x, valid, weight)

        def to_theta(rhs: np.ndarray) -> np.ndarray:
            return best.normal_inverse @ (best.lift.T @ rhs)

        def report(t: np.ndarray, springs: ReducedModel | None) -> np.ndarray:
            return self._report(best, t, theta_cov, min_force_n, springs)[0]

        return factor_effects(self.model_, self.factors_, self.changes_, best.active, theta, normal, project, to_theta,
                              report)

    def _between_states(self, candidates: Iterable[_Candidate], best: _Candidate, values: np.ndarray, noise2: float,
                        min_force_n: float, n_valid: int) -> np.ndarray:
        """(B + U, B + U) mm^2: what the contact states the field supports add to the best state's covariance (Akaike
        weights exp(-(rss / s^2 + 2 p) / 2), normalised over the states): each state's spread around the reported
        values and, for the bilateral states, its own covariance beyond the best's (the model-averaged covariance),
        kept positive semi-definite (never below the best state's). Zero without a noise level (a noise-free field
        decides its contact state).

        s^2 is the larger of the field's noise level and the residual's own (:meth:`_select`'s, which picked the
        best by the same criterion): where the model fits worse than the noise (a part the model does not make), an
        Akaike weight at the stated noise set the best state hundreds of units above another and overflowed (a
        calibrated default-hood scan: exp(+700), the estimate refused with NaN); at the residual's level the best is
        the states' minimum, and the others weigh what the residual supports.

        The own covariances matter where the best state has a pad lifted that may touch lightly: its fit leaves the
        pad's force out, so the bilateral states absorb that force's field, while the touching fit that covers it
        has nearly the same values but larger variances (five parts of the coarse hood with a 1.5-4.4 N touch: with
        the spread alone LOCK_R held 86.7 % of its errors inside the 95 % interval, up to 4.3 std off). A pad's value
        changes meaning between the states (commanded position when touching, part's position when lifted; a light
        touch's range has its own floor in _report), so the pads take the spread only: their own covariances
        overstated the buffers' std (median |z| 0.41 on the coarse hood's validation)."""
        n = values.size
        if noise2 <= 0:
            return np.zeros((n, n))
        n_b = self.model_.n_bilateral
        candidates = list(candidates)
        scale = max(noise2, min(c.rss for c in candidates) / max(n_valid, 1))

        def criterion(cand: _Candidate) -> float:
            return cand.rss / scale + 2.0 * cand.theta.size

        low = min(map(criterion, candidates))
        own = self._report(best, best.theta, noise2 * best.normal_inverse, min_force_n)[1][:n_b, :n_b]
        added, total = np.zeros((n, n)), float(np.exp(-0.5 * (criterion(best) - low)))
        for cand in candidates:
            weight = float(np.exp(-0.5 * (criterion(cand) - low)))
            if cand is best or weight < 1e-6:
                continue
            other, covariance, _, _ = self._report(cand, cand.theta, noise2 * cand.normal_inverse, min_force_n)
            diff = np.nan_to_num(other - values)
            added += weight * np.outer(diff, diff)
            added[:n_b, :n_b] += weight * (covariance[:n_b, :n_b] - own)
            total += weight
        eigval, eigvec = np.linalg.eigh(0.5 * (added + added.T) / total)
        return (eigvec * np.clip(eigval, 0.0, None)) @ eigvec.T

    def _margins(self, cand: _Candidate) -> np.ndarray:
        """(S,) mm, how far each spring is from changing state: compression f / k of an active spring, the gap of a
        free spring of a touching pad, and for a lifted pad the height of a spring above the pad's lowest one."""
        model = self.model_
        n_b = model.n_bilateral
        u = cand.lift @ cand.theta + cand.offset
        f = u[n_b:]
        height = model.z0 + model.Sa @ u[:n_b] + model.H @ f - model.preload
        pads = np.unique(model.pad_of[cand.active])
        b = np.full(self.touching_pads_.shape[1], np.nan)
        b[pads] = cand.theta[n_b:]
        lowest = np.array([height[model.pad_of == p].min(initial=np.inf) for p in range(b.size)])
        reference = np.where(np.isnan(b), lowest, b)[model.pad_of]
        return np.where(cand.active, f / model.k, np.abs(height - reference))

    def _improve(self, candidates: dict[bytes, _Candidate], problem: tuple, cache: dict) -> None:
        """Local search: restart the active-set iteration from one-spring flips of the best candidate (the
        ``MAX_FLIPS`` springs closest to changing state) while that finds a better fit. With noise, a state whose
        conditions hold within tolerance can stop the iteration early."""
        for _ in range(2 * self.model_.k.size):
            best = min(candidates.values(), key=lambda c: c.rss)
            improved = False
            for spring in np.argsort(self._margins(best))[:MAX_FLIPS]:
                start = best.active.copy()
                start[spring] = not start[spring]
                cand = self._active_set(start, problem, cache)
                if cand is not None and cand.active.tobytes() not in candidates:
                    candidates[cand.active.tobytes()] = cand
                    improved |= cand.rss < best.rss
            if not improved:
                return

    @staticmethod
    def _select(candidates: list[_Candidate], n_valid: int) -> _Candidate:
        """Best fit, penalised by its number of unknowns (an extra touching pad must earn its keep against noise)."""
        best_rss = min(c.rss for c in candidates)
        sigma2 = best_rss / max(n_valid, 1)
        return min(candidates, key=lambda c: (c.rss + 2.0 * sigma2 * c.theta.size, c.theta.size))

    def _report(
        self, cand: _Candidate, theta: np.ndarray, cov: np.ndarray, min_force_n: float,
        springs: ReducedModel | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Values (B + U,) mm, their covariance (B + U, B + U) mm^2, lifted flags (B + U,) and unseen flags (U,) from a
        solved candidate; a touching pad with a total force below ``min_force_n`` (N) is reported lifted, one whose
        compression the field cannot show is reported lifted and flagged unseen. ``springs``: the reduced model whose
        pad springs (z0 + H f, Sa, preload) a lifted pad's position is read from (a factor's changed model, for the
        part it makes); None: the model's.

        Every value is affine in theta (a state, a touching pad's position, or a lifted pad's lowest spring height),
        so the covariance is jac cov jac^T; a light-touch pad's variance is raised to cover the range its commanded
        position may take (its correlations scaled alike)."""
        model = self.model_
        n_b = model.n_bilateral
        n_pads = self.touching_pads_.shape[1]
        values = np.empty(n_b + n_pads)
        jac = np.zeros((n_b + n_pads, theta.size))
        floor = np.zeros(n_b + n_pads)  # smallest std a value may state (light touch)
        values[:n_b] = theta[:n_b]
        jac[:n_b, :n_b] = np.eye(n_b)
        lifted = np.zeros(n_b + n_pads, dtype=bool)
        unseen = np.zeros(n_pads, dtype=bool)
        u = cand.lift @ theta + cand.offset
        f = u[n_b:]
        changed = model if springs is None else springs
        preload = changed.preload
        # lifted positions as at the reference temperature
        z = changed.z0 + changed.H @ f - self.pad_shift_ + changed.Sa @ u[:n_b]
        # dz/dtheta, for a lifted pad's position.
        dz = model.Sa @ cand.lift[:n_b] + model.H @ cand.lift[n_b:]
        touching = list(np.unique(model.pad_of[cand.active]))
        for pad in range(n_pads):
            springs = np.flatnonzero(model.pad_of == pad)
            compression = float(np.sum(f[springs] / model.k[springs])) if springs.size else 0.0
            grad = (cand.lift[n_b + springs] / model.k[springs, None]).sum(axis=0)
            compression_std = np.sqrt(max(float(grad @ cov @ grad), 0.0))
            if pad in touching and compression > LIFTED_SIGMAS * compression_std:
                col = n_b + touching.index(pad)
                values[n_b + pad] = theta[col]
                jac[n_b + pad, col] = 1.0
                if float(f[springs].sum()) < min_force_n:
                    # Too light a touch to tell from lifted on a measured field: the commanded position is at most
                    # the one at which the pad just carries this force (the value, flagged lifted) and may be as low
                    # as the part's position there (the std covers that range).
                    lifted[n_b + pad] = True
                    floor[n_b + pad] = values[n_b + pad] - float(np.min(z[springs] - preload[springs]))
                continue
            lifted[n_b + pad] = True
            unseen[pad] = pad in touching
            if springs.size == 0:
                values[n_b + pad] = np.nan
                floor[n_b + pad] = np.nan
                continue
            position = z[springs] - preload[springs]
            k = springs[int(np.argmin(position))]
            values[n_b + pad] = position.min()
            jac[n_b + pad] = dz[k]
        covariance = jac @ cov @ jac.T
        std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            raise_by = np.where(floor > std, floor / np.where(std > 0, std, 1.0), 1.0)
        raise_only = np.isfinite(raise_by) & (std > 0)
        raise_by = np.where(raise_only, raise_by, 1.0)
        covariance = covariance * np.outer(raise_by, raise_by)
        bare = (std == 0) & (floor > 0)
        covariance[bare, bare] = floor[bare] ** 2
        nan = np.isnan(floor)
        covariance[nan, :] = np.nan
        covariance[:, nan] = np.nan
        return values, covariance, lifted, unseen
