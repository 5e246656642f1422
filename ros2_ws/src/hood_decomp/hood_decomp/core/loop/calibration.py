"""Calibration of the reduced model to the real part from fields with known settings, and reference-relative fields.

A model never matches the real part: on the hood, CalculiX's S8R unit responses differ from the embedded shell's by
1-2 %, and a real part's sheet thickness, pad stiffness and preload or gas-spring force differ from the drawing's.
Where a parameter is weakly observable those percent become tenths of a millimetre in the estimates (issue 16).

Calibration (``hood-decomp calibrate``) takes entries (a field of the part in a known setting, e.g. the reference
state and +- each parameter moved one at a time by a dial gauge or the robot, as in the paper's experiment) and fits,
in this order:

1. **Physical factors** through the FE model (:func:`factor_names`): the compliance scale (1 / Young's modulus: it
   scales the load and pad-force responses, not the unit boundary motions), the gas-spring force scale, the thickness
   of each sheet group (outer skin, inner panel, reinforcements; through the reduced model's finite-difference
   sensitivity to it, one refactorisation per group, :func:`core.fe.solver.thickness_sensitivities`), and per pad its
   stiffness (log scale) and preload (mm). Levenberg-Marquardt with finite-difference sensitivities on the reduced
   model: each evaluation is the exact pad contact of every entry plus superposition, no refactorisation. A Gaussian
   prior (:data:`PRIOR_STD`) keeps factors the entries do not determine at nominal.
2. **A low-rank correction** of the unit responses on the skin where the physical factors leave a residual above the
   noise: per skin node, the residual of entry j is regressed on x_j = (1, a_j, F_j / 1 kN) (bilateral states a,
   total pad forces F of the calibrated physics): Delta (N, 1 + B + U) = corrections of the load response, of each
   unit response and of each pad's response per newton. Delta is whitened by (X^T X)^(1/2), where pure noise has
   i.i.d. entries of the noise level sigma, and truncated to the singular values above
   :data:`RANK_SIGMAS` x sigma (sqrt(N) + sqrt(1 + B + U)) (the largest a noise matrix reaches): only structure the
   noise cannot make is kept.

Judged by leave-one-out: each entry is predicted by the calibration fitted on the others (its RMS error is recorded).
What the calibrated model still gets wrong is measured there too and stated: the **model discrepancy**
(:func:`discrepancy_modes`), a low-rank covariance of the skin field built from the leave-one-out residuals on the
smooth modes, scaled to a part anywhere in the bases' range, each curvature counted once; beside it the rows'
expected noise (:func:`discrepancy_noise_modes`), which every estimate nets along its own gains (the entries' noise
is not the part's), and the calibrated model's own error from the entries' noise at a part (its correction, by a
parametric bootstrap, and its physical factors), which it adds. The bases carry the three (``Bases.discrepancy``,
``discrepancy_noise``, ``calibration_noise``) and every estimate's covariance and the within-model test count them
as a field error.
Honest calibration:

- too few entries for what is fitted (a response no two other entries move, so leave-one-out cannot judge it) is
  refused naming the parameter (:class:`~hood_decomp.errors.CalibrationError`);
- an entry whose known setting disagrees with the others (a wrong dial reading) is refused naming the entry. The test
  (leave-one-out): with the physical factors fitted on the *other* entries, the setting that best explains the entry's
  field along the parameters it moves (least squares on the model's sensitivities at its state) differs from the known
  setting by more than :data:`SETTING_RTOL` of the move plus :data:`SETTING_ATOL_MM` plus
  :data:`SETTING_SIGMAS` standard deviations of that fit under the entry's error model (its node noise with the
  smoothing's correlation and, for a scan, the registration's pose error). The tolerance covers the model error
  that the physical factors leave in a response (no correct entry of the CalculiX stand-in calibrations in
  benchmarks/RESULTS.md and the tests is refused); the physical factors cannot absorb a wrong reading because they
  do not scale the unit motions.

Reference-relative estimation (``--reference``): a field of a part in a known state is subtracted and the model's
own field for that state added back, so a static model error (in the load response, the paper's protocol) cancels
(:func:`relative_field`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from hood_decomp.core.fe.contact import contact_state
from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, solve_members, validation_plan
from hood_decomp.core.fe.model import PartModel
from hood_decomp.core.fe.solver import (
    ShellSolver,
    build_solver,
    physical_responses,
    thermal_moves,
    thickness_sensitivities,
)
from hood_decomp.core.method.bases import Bases, build_bases
from hood_decomp.core.method.model_spread import PhysicalResponses, apply_factors, factor_names
from hood_decomp.core.method.residual import DEFAULT_NOISE_MM, node_variance, ring_incidence, skin_adjacency
from hood_decomp.core.method.surface_reading import ReadingOfBasis, SurfaceGradient, slide
from hood_decomp.core.types import DisplacementField, ReducedModel, SkinSurface, fingerprint
from hood_decomp.errors import CalibrationError

logger = logging.getLogger(__name__)

#: prior standard deviations of the physical factors (Gaussian, about nominal): compliance (log), gas-spring force
#: (relative), sheet thickness (log), pad stiffness (log), pad preload (mm)
PRIOR_STD = {"compliance": 0.1, "gas_spring": 0.2, "thickness": 0.1, "pad_stiffness": 0.5, "preload": 0.3}
#: relative finite-difference step of the physical factors' sensitivities
FD_STEP = 1e-4
#: singular values of the whitened correction kept above this many times the largest of a pure-noise matrix
RANK_SIGMAS = 1.0
#: setting test of an entry (module docstring): relative tolerance of a move, absolute tolerance (mm), sigmas
SETTING_RTOL = 0.08
SETTING_ATOL_MM = 0.01
SETTING_SIGMAS = 4.0
#: a tolerance above this fraction of the move is said on the log (the entry checks its setting only loosely)
SETTING_LOOSE = 0.25
#: smooth skin modes the correction lives in (:func:`smooth_modes`)
SMOOTH_MODES = 100
#: total pad force unit of the correction's regressors (N): the pad columns of Delta are per kN
FORCE_UNIT_N = 1000.0
#: states drawn over the range at which the entries' noise in the calibrated model is carried to a part
#: (:meth:`_Problem.correction_spread`, :meth:`_Problem.factor_noise`)
RANGE_SAMPLES = 32
#: the correction's parametric bootstrap (:meth:`_Problem.correction_spread`): draws and seed
BOOTSTRAP_DRAWS = 40
BOOTSTRAP_SEED = 16


@dataclass(frozen=True)
class CalibrationEntry:
    """One calibration entry: a field of the part (N,) mm in a known setting (P,) mm (names order of the bases'
    parameters; unset parameters 0). name: how the entry is named in messages (its file, or "entry 3")."""

    name: str
    field: DisplacementField
    setting: np.ndarray


@dataclass(frozen=True)
class Calibration:
    """A fitted calibration. factors: name -> value (see :func:`factor_names`); factor_std: their calibration std
    (:func:`factor_std`: the fit's or the jackknife's over the leave-one-out fits, the larger); correction:
    (N, 1 + B + U) mm per unit regressor; rank: the correction's rank; entries: entry names;
    loo_rms_mm: (M,) leave-one-out prediction RMS per entry; noise_mm: the noise level used; residual_rms_mm: (M,)
    in-sample RMS after the calibration; setting_error_mm: (M,) largest setting discrepancy of the entry's test;
    discrepancy: (N, k) mm the model discrepancy modes (:func:`discrepancy_modes`); rough_rms_mm: the leave-one-out
    residual RMS outside the smooth modes beyond the noise (not in the discrepancy: 0 when the noise explains it);
    local_mm2: (N,) mm^2 where that rough model error lies, per node on the scale of a one-ring
    (:func:`local_discrepancy`); discrepancy_noise: (N, K) mm the discrepancy rows' expected noise
    (:func:`discrepancy_noise_modes`, subtracted along each estimate's gains); calibration_noise: (N, r) mm the
    calibrated model's error from the entries' noise in its correction and its factors (added)."""

    factors: dict[str, float]
    factor_std: dict[str, float]
    correction: np.ndarray
    rank: int
    entries: tuple[str, ...]
    loo_rms_mm: np.ndarray
    noise_mm: float
    residual_rms_mm: np.ndarray
    setting_error_mm: np.ndarray
    discrepancy: np.ndarray
    rough_rms_mm: float
    local_mm2: np.ndarray
    discrepancy_noise: np.ndarray | None = None
    calibration_noise: np.ndarray | None = None

    def error_terms(self) -> dict[str, np.ndarray | None]:
        """What the calibrated bases state about this calibration's model error, as :func:`rebuild_bases` takes it:
        discrepancy, discrepancy_local, discrepancy_noise, calibration_noise."""
        return {"discrepancy": self.discrepancy, "discrepancy_local": self.local_mm2,
                "discrepancy_noise": self.discrepancy_noise, "calibration_noise": self.calibration_noise}

    def record(self) -> dict:
        """The calibration as JSON-ready data (what the bases file records): factors, rank, entries with their
        leave-one-out and in-sample error, the noise level, the model discrepancy's rank and RMS, and an id
        (fingerprint of all of it, the correction and the discrepancy modes)."""
        body = {
            "factors": self.factors, "factor_std": self.factor_std, "rank": self.rank, "noise_mm": self.noise_mm,
            "entries": [{"name": n, "loo_rms_mm": float(loo), "residual_rms_mm": float(res),
                         "setting_error_mm": float(err) if np.isfinite(err) else None}
                        for n, loo, res, err in zip(self.entries, self.loo_rms_mm, self.residual_rms_mm,
                                                    self.setting_error_mm, strict=True)],
            "loo_rms_mm": float(np.sqrt(np.mean(self.loo_rms_mm**2))),
            "discrepancy": {"rank": int(self.discrepancy.shape[1]),
                            "rms_mm": float(np.sqrt(np.sum(self.discrepancy**2) / self.discrepancy.shape[0])),
                            "rough_rms_mm": self.rough_rms_mm,
                            "local_rms_mm": float(np.sqrt(np.mean(self.local_mm2)))},
        }
        terms = {"noise_rms_mm": self.discrepancy_noise, "calibration_noise_rms_mm": self.calibration_noise}
        body["discrepancy"].update({key: float(np.sqrt(np.sum(value**2) / value.shape[0]))
                                    for key, value in terms.items() if value is not None})
        body["id"] = fingerprint(json.dumps(body, sort_keys=True), self.correction, self.discrepancy, self.local_mm2,
                                 *(value for value in terms.values() if value is not None))
        return body


def one_at_a_time(n_params: int, moves: tuple[float, ...] = (0.8,)) -> np.ndarray:
    """The usual calibration plan: the reference (all 0) and +-each move (mm) of each parameter alone,
    (1 + 2 P len(moves), P); 13 entries for the hood with one move, 25 with two."""
    settings = [np.zeros(n_params)]
    for move in moves:
        for i in range(n_params):
            for sign in (1.0, -1.0):
                setting = np.zeros(n_params)
                setting[i] = sign * move
                settings.append(setting)
    return np.array(settings)


def with_correction(reduced: ReducedModel, correction: np.ndarray, normals: np.ndarray) -> ReducedModel:
    """The reduced model with a skin correction (N, 1 + B + U) mm: of w0, each unit response, and each pad's response
    per kN (spread on every spring of the pad: the pad's total force carries it). normals (N, 3): the 3D fields move
    along the skin normal."""
    B = reduced.n_bilateral
    d0, dR, dP = correction[:, 0], correction[:, 1:1 + B], correction[:, 1 + B:] / FORCE_UNIT_N
    dG = dP[:, reduced.pad_of]
    return replace(
        reduced, w0=reduced.w0 + d0, R=reduced.R + dR, G=reduced.G + dG,
        w0_3d=reduced.w0_3d + normals * d0[:, None], R_3d=reduced.R_3d + normals[:, :, None] * dR[:, None, :],
        G_3d=reduced.G_3d + normals[:, :, None] * dG[:, None, :],
    )


def normal_fields(reduced: ReducedModel, settings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Skin normal fields (m, N) mm and total pad forces (m, U) N at commanded settings (m, P) mm: the exact pad
    contact and superposition of :func:`core.fe.ensemble.solve_members`, without its 3D fields (the fit's hot path)."""
    B = reduced.n_bilateral
    U = len(reduced.names) - B
    forces = np.array([contact_state(reduced, state[:B], state[B:]).f for state in settings])
    totals = np.stack([forces[:, reduced.pad_of == u].sum(axis=1) for u in range(U)], axis=1)
    return reduced.w0[None, :] + settings[:, :B] @ reduced.R.T + forces @ reduced.G.T, totals


def _noise(field: DisplacementField) -> float:
    """The noise level (mm) of a field: its error model's median node std, its noise_rms, else the default."""
    errors = field.errors
    if errors.kind != "none":
        std = np.asarray(errors.node_std, float)
        std = std[np.isfinite(std)]
        if std.size and np.median(std) > 0:
            return float(np.median(std))
    if np.isfinite(field.noise_rms) and field.noise_rms > 0:
        return float(field.noise_rms)
    return DEFAULT_NOISE_MM


def _entry_errors(field: DisplacementField, skin: SkinSurface, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """(variance (N,) mm^2, modes (N, k) mm): a calibration entry's errors as the setting test weighs them and
    :meth:`_Problem.without_pose` takes its pose error out by. Each node's variance
    times its correlation sum (the smoothing's correlated noise, as an estimate's covariance counts it) and the
    registration's pose modes: a scanned entry's pose error looks like a rigid turn of the part, which a lock, buffer
    or hinge move nearly is; with white node noise alone correct scanned entries of the coarse hood were refused
    (HINGE_X 0.02-0.26 mm beyond the tolerance at 0.05 mm markers). A field without an error model: white at
    ``noise``."""
    n = skin.n_nodes
    errors = field.errors
    if errors.kind == "none":
        return np.full(n, noise**2), np.zeros((n, 0))
    variance, correlation = node_variance(errors, n)
    modes = errors.registration_modes(skin.points, skin.normals) if errors.has_pose else np.zeros((n, 0))
    return variance * correlation, modes


class _Problem:
    """The entries as arrays: Y (M, N) with 0 where unseen, mask (M, N), settings (M, P), noise (M,); errors: per
    entry its (variance, modes) of :func:`_entry_errors`."""

    def __init__(self, entries: list[CalibrationEntry], reduced: ReducedModel, physics: PhysicalResponses,
                 skin: SkinSurface):
        self.reduced, self.physics, self.modes = reduced, physics, np.zeros((skin.n_nodes, 0))
        self.names = tuple(e.name for e in entries)
        values = np.array([np.asarray(e.field.normal_displacement, float) for e in entries])
        self.mask = np.isfinite(values)
        self.Y = np.where(self.mask, values, 0.0)
        self.settings = np.array([np.asarray(e.setting, float) for e in entries])
        self.noise = np.array([_noise(e.field) for e in entries])
        self.prior = np.array([PRIOR_STD[name.split(":")[0]] for name in factor_names(reduced, physics)])
        self.errors = [_entry_errors(e.field, skin, level) for e, level in zip(entries, self.noise, strict=True)]
        # per scanned entry (U (N, 6), (U^T V^-1 U + I)^-1 U^T V^-1 on its seen nodes): its pose error's best fit
        self._poses = [None if modes.shape[1] == 0 else
                       (modes, np.linalg.solve((modes.T * (seen / variance)) @ modes + np.eye(modes.shape[1]),
                                               modes.T * (seen / variance)))
                       for (variance, modes), seen in zip(self.errors, self.mask, strict=True)]

    def without_pose(self, rows: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """Residuals (m, N) of entries ``rows`` (0 where unseen) less the pose error each scanned entry's registration
        states that best explains them (z ~ N(0, I) on its pose modes, regularised least squares under its node
        variance): a scan's pose error is no model error. Fitted as one (13 default-hood scans, 8 markers at 0.02
        mm), it became a discrepancy of 0.023 mm RMS and every stated std grew 3-20 x. Fields: unchanged."""
        out = np.array(residual, dtype=float, copy=True)
        for i, row in enumerate(rows):
            if self._poses[row] is not None:
                modes, fit = self._poses[row]
                out[i] -= (modes @ (fit @ out[i])) * self.mask[row]
        return out

    def predict(self, theta: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model fields (m, N) and total pad forces (m, U) of entries ``rows`` with physical factors theta."""
        return normal_fields(apply_factors(self.reduced, self.physics, theta, full=False), self.settings[rows])

    def weighted_residual(self, theta: np.ndarray, rows: np.ndarray) -> np.ndarray:
        fields, _ = self.predict(theta, rows)
        r = self.without_pose(rows, (self.Y[rows] - fields) * self.mask[rows]) / self.noise[rows, None]
        return np.concatenate([r.ravel(), theta / self.prior])

    def fit_factors(self, rows: np.ndarray, start: np.ndarray | None = None, iterations: int = 12
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Levenberg-Marquardt on the physical factors over entries ``rows``: (theta, covariance)."""
        theta = np.zeros(len(self.prior)) if start is None else start.copy()
        r = self.weighted_residual(theta, rows)
        cost, damping = float(r @ r), 1e-3
        jac = np.zeros((r.size, theta.size))
        for iteration in range(iterations):
            for i in range(theta.size):
                step = FD_STEP * max(1.0, abs(theta[i]))
                shifted = theta.copy()
                shifted[i] += step
                jac[:, i] = (self.weighted_residual(shifted, rows) - r) / step
            normal, gradient = jac.T @ jac, jac.T @ r
            improved = False
            for _ in range(8):
                delta = np.linalg.solve(normal + damping * np.diag(np.diag(normal)), -gradient)
                trial = theta + delta
                r_trial = self.weighted_residual(trial, rows)
                if float(r_trial @ r_trial) < cost:
                    theta, r, cost = trial, r_trial, float(r_trial @ r_trial)
                    damping, improved = damping / 10.0, True
                    break
                damping *= 10.0
            logger.debug("physical factors: iteration %d cost %.6g", iteration, cost)
            if not improved or np.max(np.abs(delta)) < 1e-7:
                break
        return theta, np.linalg.inv(jac.T @ jac)

    def regressors(self, forces: np.ndarray, rows: np.ndarray, settings: np.ndarray | None = None) -> np.ndarray:
        """X (m, 1 + B + U): 1, the bilateral states and the total pad forces (kN) of entries ``rows`` (or of
        ``settings`` (m, P) mm, other states)."""
        B = self.reduced.n_bilateral
        states = self.settings[rows] if settings is None else settings
        return np.hstack([np.ones((len(rows), 1)), states[:, :B], forces / FORCE_UNIT_N])

    def fit_correction(self, theta: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The low-rank correction (N, q) from entries ``rows`` after physical factors theta, the smooth-mode
        directions it keeps (K, rank), orthonormal, and its regressors X (m, q).

        The residuals are projected on the skin's smooth modes (:attr:`modes`, orthonormal (N, K)): a model error is
        smooth, noise is not, so the noise the correction can pick up lives in K dimensions instead of N (an unseen
        node counts as no residual). C (K, q) is the least-squares regression on X, whitened by (X^T X)^(1/2) and
        truncated to the singular values above the largest of a pure-noise (K, q) matrix (:func:`truncated_fit`)."""
        residual, X = self.residuals(theta, rows)
        coefficients, kept = truncated_fit(residual, X, float(np.sqrt(np.mean(self.noise[rows] ** 2))))
        return self.modes @ coefficients, kept, X

    def residuals(self, theta: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(residuals (m, K) mm on the smooth modes, regressors X (m, q)) of entries ``rows`` after the physical
        factors theta: what the correction regresses."""
        fields, forces = self.predict(theta, rows)
        residual = self.without_pose(rows, (self.Y[rows] - fields) * self.mask[rows]) @ self.modes
        return residual, self.regressors(forces, rows)

    def correction_spread(self, theta: np.ndarray, calibrated: ReducedModel, states: np.ndarray) -> np.ndarray:
        """(N, r) mm: the calibrated model's error from the entries' noise in its correction, at parts at ``states``
        (n, P) mm: :func:`correction_bootstrap` on the entries' residuals after the physical factors theta, each
        draw's noise of each entry's level (unseen nodes and a scan's pose error taken out as from the entries).
        Every part of the plant shares this error, so leave-one-out cannot show it."""
        everything = np.arange(len(self.names))
        residual, X = self.residuals(theta, everything)
        parts = self.regressors(normal_fields(calibrated, states)[1], np.arange(len(states)), states)

        def noise(rng: np.random.Generator) -> np.ndarray:
            drawn = rng.normal(size=self.Y.shape) * self.noise[:, None] * self.mask
            return self.without_pose(everything, drawn) @ self.modes

        return self.modes @ correction_bootstrap(residual, X, float(np.sqrt(np.mean(self.noise**2))), noise, parts)

    def factor_noise(self, theta: np.ndarray, covariance: np.ndarray, states: np.ndarray) -> np.ndarray:
        """(N, r) mm: the calibrated model's error from the entries' noise in its physical factors theta (fit
        covariance (F, F)), at parts at ``states`` (n, P) mm: the field's finite-difference sensitivity along each
        principal direction of the covariance, stacked over the states (/ sqrt(n)) and reduced to the singular
        values above 1e-3 of the largest. Not reduced by what the correction would absorb of it (an upper bound)."""
        values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
        base = normal_fields(apply_factors(self.reduced, self.physics, theta, full=False), states)[0]
        columns = []
        for value, vector in zip(values, vectors.T, strict=True):
            if value <= 0:
                continue
            direction = vector * np.sqrt(value)
            step = FD_STEP / max(float(np.max(np.abs(direction))), 1e-300)
            moved = normal_fields(apply_factors(self.reduced, self.physics, theta + step * direction, full=False),
                                  states)[0]
            columns.append((moved - base) / step)  # (n, N) per unit sigma along the direction
        if not columns:
            return np.zeros((base.shape[1], 0))
        return _leading_modes(np.concatenate(columns, axis=0).T / np.sqrt(len(states)))  # of (N, F n)

    def setting_error(self, theta: np.ndarray, row: int) -> tuple[float, str, tuple[str, float] | None]:
        """The entry's setting test (module docstring) with physical factors theta fitted without it: the largest
        excess of |apparent - known| over the tolerance (mm, <= 0 passes), the parameter it is on, and (parameter,
        tolerance mm) where a tolerance exceeds :data:`SETTING_LOOSE` of the move (None: none does)."""
        setting = self.settings[row]
        moved = np.flatnonzero(setting != 0.0)
        if moved.size == 0:
            return -np.inf, "", None
        rows = np.array([row])
        base, _ = self.predict(theta, rows)
        reduced = apply_factors(self.reduced, self.physics, theta, full=False)
        sens = []
        for i in moved:
            step = 1e-3
            shifted = setting.copy()
            shifted[i] += step
            sens.append((normal_fields(reduced, shifted[None, :])[0][0] - base[0]) / step)
        J = np.array(sens).T[self.mask[row]]
        observable = np.linalg.norm(J, axis=0) > 1e-6 * max(np.linalg.norm(J), 1e-300)
        if not observable.any():
            return -np.inf, "", None
        J, moved = J[:, observable], moved[observable]
        r = (self.Y[row] - base[0])[self.mask[row]]
        # ordinary least squares; its spread under the entry's error model, the registration's pose error included.
        # Fitting the pose beside the setting (generalised least squares) leans on the part's non-rigid shape, which
        # the model's own discrepancy moves: correct scanned entries of the coarse CalculiX stand-in were refused
        gain = np.linalg.solve(J.T @ J, J.T)  # (k, n_seen): delta = gain r
        delta = gain @ r
        variance, modes = self.errors[row]
        along = gain @ modes[self.mask[row]]
        std = np.sqrt(np.einsum("kn,n,kn->k", gain, variance[self.mask[row]], gain) + np.sum(along**2, axis=1))
        tolerance = SETTING_RTOL * np.abs(setting[moved]) + SETTING_ATOL_MM + SETTING_SIGMAS * std
        excess = np.abs(delta) - tolerance
        worst, loose = int(np.argmax(excess)), int(np.argmax(tolerance / np.abs(setting[moved])))
        loosest = ((self.reduced.names[moved[loose]], float(tolerance[loose]))
                   if tolerance[loose] > SETTING_LOOSE * abs(setting[moved[loose]]) else None)
        return float(excess[worst]), self.reduced.names[moved[worst]], loosest


def _whitened(residual: np.ndarray, design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Z (K, q), (X^T X)^(-1/2) (q, q)): the least-squares coefficients of ``residual`` (m, K) on ``design`` X
    (m, q), whitened by (X^T X)^(1/2), where white noise of std sigma in the residual has i.i.d. entries sigma."""
    gram = design.T @ design
    q = gram.shape[0]
    coefficients = np.linalg.solve(gram + 1e-12 * np.trace(gram) * np.eye(q), design.T @ residual).T  # (K, q)
    values, vectors = np.linalg.eigh(gram)
    root = (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T
    inverse_root = (vectors / np.sqrt(np.clip(values, 1e-300, None))) @ vectors.T
    return coefficients @ root, inverse_root


def truncated_fit(residual: np.ndarray, design: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The correction's low-rank regression: (C (K, q) mm per unit regressor, kept (K, rank) orthonormal) of the
    residuals (m, K) mm on the smooth modes over the regressors ``design`` X (m, q), the entries' noise ``sigma`` mm.
    Whitened (:func:`_whitened`) and truncated to the singular values above :data:`RANK_SIGMAS` sigma (sqrt(K) +
    sqrt(q)), the largest a pure-noise (K, q) matrix reaches: only structure the noise cannot make is kept."""
    whitened, inverse_root = _whitened(residual, design)
    u, s, vt = np.linalg.svd(whitened, full_matrices=False)
    threshold = RANK_SIGMAS * sigma * (np.sqrt(residual.shape[1]) + np.sqrt(design.shape[1]))
    rank = int(np.sum(s > threshold))
    return (u[:, :rank] * s[:rank]) @ vt[:rank] @ inverse_root, u[:, :rank]


@lru_cache(maxsize=8)
def noise_singular_values(rows: int, columns: int, draws: int = 2000, seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """(min(rows, columns),) E[s_i^2], descending, read-only: the expected squared singular values of a (rows,
    columns) matrix of i.i.d. N(0, 1) entries, by Monte Carlo (``draws`` matrices, a fixed seed: the same numbers
    every call; kept per shape, 0.1-0.3 s each)."""
    rng = np.random.default_rng(seed)
    expected = np.mean(np.linalg.svd(rng.normal(size=(draws, rows, columns)), compute_uv=False) ** 2, axis=0)
    expected.flags.writeable = False
    return expected


def correction_bootstrap(residual: np.ndarray, design: np.ndarray, sigma: float,
                         noise: Callable[[np.random.Generator], np.ndarray], parts: np.ndarray,
                         draws: int = BOOTSTRAP_DRAWS, seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """(K, r) mm: the error the entries' noise leaves in :func:`truncated_fit` at parts, by a parametric bootstrap
    **centred on the signal**, as a low-rank covariance on the smooth modes.

    residual: (m, K) mm the entries' residuals on the modes (after the physical factors); design: (m, q) their
    regressors X; sigma: mm the noise level of the truncation; noise: one draw (m, K) mm of the entries' noise on the
    modes; parts: (n, q) the regressors of parts over the range. Returns the leading modes (:func:`_leading_modes`)
    of the deviations' second moment over ``draws`` draws and the n parts.

    The error to state is trunc(T + eps) - trunc(T) (T the true residuals' whitened regression, eps the entries'
    noise): the truncation decides per direction, so a direction of T near the threshold is kept or dropped by the
    draw of the noise, and that choice is most of the error (a fixed-subspace formula gave a quarter to a third of it
    along the bilateral gains; benchmarks/RESULTS.md, session 11). A bootstrap drawn around the fitted, truncated
    correction (sessions 11-20) has no such direction: what it dropped is not there for the noise to push over the
    threshold, and what it kept lies far above it. On the coarse CalculiX stand-in (10 families, along the bilateral
    gains) it stated 0.40-0.65 x the variance measured (calibrated from the noisy entries against from the same
    entries without their noise) and 0.41-0.83 x what a bootstrap centred on the noise-free entries states
    (benchmarks/RESULTS.md, session 21).
    The centre here is the closest the entries give to T: the untruncated whitened fit Z = U S V^T with each squared
    singular value less what pure noise puts in that place of the order, s_i^2 - sigma^2 E[s_i^2 | noise]
    (:func:`noise_singular_values`), clipped at 0: the noise's energy taken out where it sits. On the stand-in:
    0.83-0.93 x the variance measured, 0.84-1.18 x the noise-free-centred bootstrap; on known signals (numpy Monte
    Carlo of the whole calibration): 1.00-1.22 x the actual, pure noise included. Each draw is the centre plus
    fresh noise, truncated again, minus the centre truncated (the noise's deviation, not the centre's distance to
    the calibration's own correction). Rejected, measured: the entries as measured (their noise counted twice:
    1.07-1.57 x the noise-free-centred on the stand-in, 1.35-1.73 x on known hood-like signals, 63 x on pure noise,
    whose sqrt(2) sigma crosses the threshold); one debiasing K sigma^2 for every singular value (0.58-0.76 x the
    measured on the stand-in; 7 x on pure noise); deviations from the draws' mean (less than the fitted centre's)."""
    whitened, inverse_root = _whitened(residual, design)
    u, s, vt = np.linalg.svd(whitened, full_matrices=False)
    signal = np.sqrt(np.clip(s**2 - sigma**2 * noise_singular_values(*whitened.shape), 0.0, None))
    centre = design @ ((u * signal) @ vt @ inverse_root).T  # (m, K) the centre's residuals
    reference = truncated_fit(centre, design, sigma)[0]
    rng = np.random.default_rng(seed)
    deviations = [(truncated_fit(centre + noise(rng), design, sigma)[0] - reference) @ parts.T for _ in range(draws)]
    return _leading_modes(np.hstack(deviations) / np.sqrt(draws * len(parts)))


def discrepancy_modes(residuals: np.ndarray, settings: np.ndarray, modes: np.ndarray, variance: np.ndarray,
                      fourth: np.ndarray) -> np.ndarray:
    """The model discrepancy D (N, k) mm of a calibration: what the calibrated model gets wrong on a part anywhere
    in the range, as a low-rank skin covariance D D^T (delta = D z, z ~ N(0, I_k)).

    residuals: (M, N) mm leave-one-out residuals of the entries (0 where unseen); settings: (M, P) mm; modes:
    (N, K) orthonormal smooth skin modes; variance, fourth: (P,) mm^2 and mm^4, E[a_i^2] and E[a_i^4] of a part's
    state over the range (uniform on [l, u]: (l^2 + l u + u^2) / 3 and (u^5 - l^5) / (5 (u - l))).

    A model error grows with the state: delta(a) ~ delta_0 + sum_i (a_i g_i + a_i^2 h_i) (g_i: the error per mm
    along parameter i, h_i its curvature). The rows of D^T, taken on the smooth modes (a model error is smooth, the
    noise is not), each one sample of a term, weighted so that the sum of their outer products is the second moment
    over the range (exact for one-at-a-time plans):

    - the reference entries (setting 0; else the entry closest to it): delta_0;
    - a +-m pair of one parameter (the usual plan) splits into its odd part, the slope (r_+ - r_-) / 2m, times
      sqrt(E[a_i^2]), and its even part, the curvature, ((r_+ + r_-) / 2 - r_0) / 2m^2, times sqrt(E[a_i^4]).
      Leave-one-out extrapolates a left-out +m from -m, so a curvature q a^2 leaves 2 q m^2 in *both* residuals of
      the pair, while the full calibration (slope 0 over the pair) leaves q a^2: taken as slopes, as before, the pair
      counted it about 2.4 times in std (LOCK_L 98.7 % covered; benchmarks/RESULTS.md, session 8); the 2 m^2 takes
      it once. Several pairs of one parameter (+-0.8 and +-0.4 mm: 25 entries) sample the same g_i and h_i: they
      give one slope and one curvature row, the pairs combined by least squares (weights m^2 and m^4, the inverse
      of their noise variance), not a row per pair, whose inner pair's rows divided the noise by 2 m and 2 m^2 and
      stated 4-9 x the error variance (98.2 % covered on the CalculiX stand-in, 100 % for HINGE_X and LOCK_L;
      benchmarks/RESULTS.md, session 10). The rows' share is 2 (pairs) / (the entries moving the parameter);
    - any other entry j: (r_j - r_0) / |s_j|, an error per mm along u_j = s_j / |s_j|, weighted by
      w_j = sum_i u_ji^2 variance_i / n_i (n_i = sum_j u_ji^2 over the moved entries).

    **The estimate's own uncertainty is kept, not subtracted.** Each row is the model error's term plus the noise
    of the entries it is made from (eps, estimated from one pair: about one degree of freedom per term). Its
    unbiased estimate would subtract the noise's expected energy (C C^T - N); the predicted part then needs the
    uncertainty of that estimate on top (+ N, the covariance of the rows' estimation error), so D D^T = C^T C, the
    rows as measured. Subtracting the noise instead (sessions 4-8, taking the estimate as exact) covered 88-96 % per
    parameter once the over-count was gone (HINGE_Y 88 %) and alarmed on 3.8 % of good parts
    (benchmarks/RESULTS.md, session 9).

    M entries give a covariance estimate with about M degrees of freedom (k <= M directions): the within-model test
    refers its statistic to a Hotelling-type law with that many (:func:`core.method.residual.check_residual`, the
    bases' ``discrepancy_dof``), not to a chi-square that takes the estimate as exact.

    The rows' noise is not the part's error, though: the part's own measurement term already carries noise, and the
    calibrated model's share of the entries' noise is the correction's estimation error, not a left-out entry's
    noise. :func:`discrepancy_noise_modes` states the rows' expected noise W W^T, which the estimate's covariance
    subtracts along its own gains (:func:`core.method.estimation.parameter_covariance`), and
    :meth:`_Problem.correction_spread` and :meth:`_Problem.factor_noise` the calibrated model's own error from the
    entries' noise at a part's state, which it adds."""
    return modes @ (_discrepancy_rows(settings, variance, fourth) @ (residuals @ modes)).T


def _leading_modes(stacked: np.ndarray) -> np.ndarray:
    """(n, r) the low-rank factor U S of ``stacked`` (n, m) that keeps its singular values above 1e-3 of the
    largest: a covariance stacked @ stacked.T stated in r modes."""
    u, s, _ = np.linalg.svd(stacked, full_matrices=False)
    keep = s > 1e-3 * s[0] if s.size and s[0] > 0 else np.zeros(s.size, bool)
    return u[:, keep] * s[keep]


def _discrepancy_rows(settings: np.ndarray, variance: np.ndarray, fourth: np.ndarray) -> np.ndarray:
    """The rows A (k, M) of :func:`discrepancy_modes`: D^T = A (leave-one-out residuals on the modes)."""
    M = settings.shape[0]
    size = np.linalg.norm(settings, axis=1)
    reference = size == 0.0
    if not reference.any():
        reference = size == size.min()
    base = reference / reference.sum()
    moved = np.flatnonzero(~reference)
    directions = settings[moved] / size[moved, None]
    counts = np.sum(directions**2, axis=0)
    eye = np.eye(M)
    single = [j for j in moved if np.count_nonzero(settings[j]) == 1]
    pairs = []
    for j in single:
        partner = [k for k in single if k > j and np.array_equal(settings[k], -settings[j])
                   and all(k not in pair and j not in pair for pair in pairs)]
        if partner:
            pairs.append((j, partner[0]))
    paired = {j for pair in pairs for j in pair}
    rows = [base]
    for i in range(settings.shape[1]):
        own = [(j, k) for j, k in pairs if settings[j, i] != 0.0]
        if not own:
            continue
        # one slope and one curvature row per parameter, whatever its number of pairs: the pairs' estimates of the
        # same g_i (h_i) combined by least squares (noise var 1 / m^2 (1 / m^4) each), not one row per pair
        m = np.array([abs(settings[j, i]) for j, _ in own])
        share = 2.0 * len(own) / counts[i]
        slope = sum(w * (eye[j] - eye[k]) / (2.0 * mk) for (j, k), mk, w in zip(own, m, m**2 / np.sum(m**2),
                                                                              strict=True))
        curvature = sum(w * ((eye[j] + eye[k]) / 2.0 - base) / (2.0 * mk * mk)
                        for (j, k), mk, w in zip(own, m, m**4 / np.sum(m**4), strict=True))
        rows.append(slope * np.sqrt(share * variance[i]))
        rows.append(curvature * np.sqrt(share * fourth[i]))
    for j, u in zip(moved, directions, strict=True):
        if j not in paired:
            weight = (u**2 / np.where(counts > 0, counts, 1.0)) @ variance
            rows.append((eye[j] - base) * np.sqrt(weight) / size[j])
    return np.array(rows)


def loo_smoother(design: np.ndarray) -> np.ndarray:
    """L (M, M): the leave-one-out residuals' dependence on the entries' noise through a least-squares regression on
    ``design`` (M, q): r_j = sum_k L_jk eps_k with L_jj = 1 and L_jk = -x_j^T (X_-j^T X_-j)^+ x_k (the left-out
    entry's own noise, minus the fit of the others' noise at its regressors)."""
    M = design.shape[0]
    smoother = np.eye(M)
    for j in range(M):
        others = np.delete(np.arange(M), j)
        gram = design[others].T @ design[others]
        smoother[j, others] = -design[j] @ np.linalg.pinv(gram) @ design[others].T
    return smoother


def discrepancy_noise_modes(settings: np.ndarray, modes: np.ndarray, variance: np.ndarray, fourth: np.ndarray,
                            noise: np.ndarray, smoother: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """W (N, K) mm: the expected noise of the discrepancy's rows, E[noise part of D D^T] = W W^T.

    settings, modes, variance, fourth: as :func:`discrepancy_modes`; noise: (M,) mm the entries' white noise std;
    smoother: (M, M) :func:`loo_smoother` of the correction's regression; kept: (K, r) orthonormal, the smooth-mode
    directions the correction keeps. On the kept directions a leave-one-out residual is L eps (the left-out entry's
    noise and the others' through the refit), on the rest the entry's own noise alone: with A the rows,
    c_kept = ||A L diag(noise)||_F^2 and c_drop = ||A diag(noise)||_F^2 per mode, white within each part.

    Why it is stated and not subtracted here: D D^T has rank k (the rows) in K = 100 modes, so the rows' noise
    (c per mode, c K in all) sits in the rows' k directions; subtracting c I and clipping to a covariance would leave
    (K - k) / K of it. Along a fixed gain g, g^T D D^T g - g^T W W^T g is unbiased, which is where the estimate
    takes it: along each parameter's gain (:func:`core.method.estimation.parameter_covariance`). Measured before
    (benchmarks/RESULTS.md, session 10): the rows' noise was 1.8-2.5 x the part's measurement variance along the
    bilateral gains, counted on top of the part's own noise (LOCK_L stated 1.76 x its actual error variance)."""
    rows = _discrepancy_rows(settings, variance, fourth)
    c_kept = float(np.sum((rows @ smoother * noise) ** 2))
    c_drop = float(np.sum((rows * noise) ** 2))
    complement = np.linalg.svd(np.eye(modes.shape[1]) - kept @ kept.T)[0][:, :modes.shape[1] - kept.shape[1]]
    return modes @ np.hstack([kept * np.sqrt(c_kept), complement * np.sqrt(c_drop)])


def local_discrepancy(residuals: np.ndarray, mask: np.ndarray, noise: np.ndarray, modes: np.ndarray,
                      skin: SkinSurface) -> np.ndarray:
    """Where the model error outside the smooth modes lies: (N,) mm^2, per node the variance of a one-ring mean of
    the leave-one-out residuals' rough part (outside ``modes``) beyond the noise's share (sigma_j^2 / ring size),
    averaged over the entries and then over each node's one-ring (13 entries are few samples per node).

    residuals: (M, N) mm leave-one-out residuals (0 where unseen); mask: (M, N) seen; noise: (M,) mm; modes: (N, K)
    orthonormal smooth modes. The discrepancy modes hold the smooth part; this rough part (near the pads on the hood,
    0.0035-0.0042 mm RMS on the CalculiX stand-in) is what only the test's one-ring part sees
    (:func:`core.method.residual.check_residual`): uniform, it left 4.4 % false alarms, concentrated at a few rings."""
    rings = ring_incidence(skin)
    rough = np.where(mask, residuals - (residuals @ modes) @ modes.T, 0.0)
    count = np.asarray(mask, float) @ rings.T  # (M, N) seen nodes per ring
    means = (rough @ rings.T) / np.maximum(count, 1.0)
    excess = np.where(count > 0, means**2 - noise[:, None] ** 2 / np.maximum(count, 1.0), 0.0)
    per_node = np.maximum(excess.sum(axis=0) / np.maximum((count > 0).sum(axis=0), 1), 0.0)
    return (rings @ per_node) / np.asarray(rings.sum(axis=1)).ravel()


def factor_std(covariance: np.ndarray, theta_loo: np.ndarray) -> np.ndarray:
    """The physical factors' calibration std (F,): the larger of the fit's own (``covariance`` (F, F), the entries'
    noise through the Gauss-Newton normal matrix and the prior) and the jackknife's over the leave-one-out fits
    ``theta_loo`` (M, F): sqrt((M - 1) / M sum_j (theta_-j - mean)^2).

    The fit's covariance counts only the entries' white noise, as if the model's shape were right; a factor the
    entries pin down only through a response the model gets wrong (a pad's preload against the S8R skin's pad
    response) moves when one entry is left out far more than that noise allows. On the CalculiX stand-in the fit's
    preload std was 0.001-0.002 mm while the calibrated pad offset (z0 - preload) was off by up to 0.020 mm; the
    jackknife's 0.005-0.027 mm followed the error family by family (benchmarks/RESULTS.md, session 8)."""
    M = theta_loo.shape[0]
    jackknife = np.sqrt((M - 1) / M * np.sum((theta_loo - theta_loo.mean(axis=0)) ** 2, axis=0))
    return np.maximum(np.sqrt(np.clip(np.diag(covariance), 0.0, None)), jackknife)


def smooth_modes(skin: SkinSurface, count: int = SMOOTH_MODES) -> np.ndarray:
    """The ``count`` smoothest skin fields (N, count), orthonormal: the lowest eigenvectors of the skin's graph
    Laplacian (edge weights 1), which resolve features down to about sqrt(skin area / count) (~100 mm on the hood)."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import eigsh

    adjacency = skin_adjacency(skin)
    laplacian = diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
    count = min(count, skin.n_nodes - 2)
    _, vectors = eigsh(laplacian.tocsc(), k=count, sigma=-1e-3, which="LM")
    return np.linalg.qr(vectors)[0]


def _check_support(problem: _Problem, entries: list[CalibrationEntry]) -> None:
    """CalibrationError when the entries cannot support the fit with leave-one-out: every response needs at least
    two entries that move it beyond the others (so that leaving one out still determines it)."""
    M = len(entries)
    names = problem.reduced.names
    B = problem.reduced.n_bilateral
    q = 1 + B + (len(names) - B)
    if M < q + 1:
        raise CalibrationError(f"calibration needs at least {q + 1} entries (the reference and each parameter moved "
                               f"at least twice: leave-one-out), got {M}")
    for i, label in enumerate(names):
        moved = int(np.sum(problem.settings[:, i] != problem.settings[0, i]) if i >= B else
                    np.sum(problem.settings[:, i] != 0.0))
        if i < B and moved < 2:
            raise CalibrationError(f"parameter {label} is moved in {moved} calibration entr"
                                   f"{'y' if moved == 1 else 'ies'}; its response needs at least 2 (leave-one-out)")
        if i >= B and len(np.unique(problem.settings[:, i])) < 3:
            raise CalibrationError(f"parameter {label} takes {len(np.unique(problem.settings[:, i]))} distinct "
                                   "values in the calibration entries; its pad needs at least 3 (leave-one-out)")


def model_physics(model: PartModel, reduced: ReducedModel, solver: ShellSolver | None = None) -> PhysicalResponses:
    """The FE responses behind ``model``'s physical factors (:class:`PhysicalResponses`): gas springs and 1 K from
    one factorisation (``solver``'s, else one built now), d(``reduced``)/d(log thickness) from one more per sheet
    group (core.fe.solver.thickness_sensitivities). ``reduced``: the reduced model of ``model`` itself."""
    return PhysicalResponses.from_solver(physical_responses(solver or build_solver(model)),
                                         thickness_sensitivities(model, reduced), thermal_moves(model))


def calibrate(reduced: ReducedModel, physics: PhysicalResponses, entries: list[CalibrationEntry],
              skin: SkinSurface, state_range: tuple[np.ndarray, np.ndarray] | None = None,
              reading: ReadingOfBasis | None = None) -> tuple[ReducedModel, Calibration]:
    """Fit physical factors, then the low-rank correction (module docstring); leave-one-out over the entries, and
    from it the model discrepancy.

    reduced: the bases' reduced model; physics: :class:`PhysicalResponses` of the same model; entries: fields in the
    skin node order with settings (P,) mm in ``reduced.names`` order; skin: the bases' skin (normals, smooth modes);
    state_range: (lower, upper) (P,) mm, the range the parts' states lie in (the bases'), over which the discrepancy
    is averaged (None: +- the largest move of each parameter in the entries); reading: what a scan reads less than
    the bases' fields (``Bases.reading()``), so that scanned entries have the scan step's bias inside the basis
    taken out as the estimator takes it out of the parts' scans (:func:`as_node_displacement`; None: the slide only).
    Returns the calibrated reduced model and the :class:`Calibration`. Raises CalibrationError naming an entry whose
    setting disagrees with the others, or what the entries do not support.
    """
    for entry in entries:
        if entry.field.model_id != reduced.model_id:
            raise CalibrationError(f"calibration entry {entry.name}: field model_id {entry.field.model_id!r} is not "
                                   f"the bases' {reduced.model_id!r}")
        if np.shape(entry.setting) != (len(reduced.names),):
            raise CalibrationError(f"calibration entry {entry.name}: setting has shape {np.shape(entry.setting)}, "
                                   f"expected ({len(reduced.names)},)")
        if np.shape(entry.field.normal_displacement) != (reduced.w0.shape[0],):
            raise CalibrationError(f"calibration entry {entry.name}: field has "
                                   f"{np.shape(entry.field.normal_displacement)} values, expected "
                                   f"({reduced.w0.shape[0]},)")
    # the skin's gradient once for every scanned entry (0.28 s at paper resolution), none for fields
    gradient = None
    if any(entry.field.errors.kind == "scan" for entry in entries):
        gradient = reading.gradient if reading is not None else SurfaceGradient.fit(skin)
    entries = [replace(entry, field=as_node_displacement(entry.field, reduced, entry.setting, gradient, reading))
               for entry in entries]
    problem = _Problem(entries, reduced, physics, skin)
    _check_support(problem, entries)
    problem.modes = smooth_modes(skin)  # after the checks: a refused calibration costs nothing
    normals = skin.normals
    M = len(entries)
    everything = np.arange(M)
    theta, covariance = problem.fit_factors(everything)
    logger.info("calibration: physical factors %s",
                dict(zip(factor_names(reduced, physics), np.round(theta, 5), strict=True)))
    loo = np.zeros(M)
    loo_residual = np.zeros_like(problem.Y)
    setting_error = np.zeros(M)
    theta_loo = np.zeros((M, theta.size))
    labels = []
    for j in range(M):
        theta_loo[j], _ = problem.fit_factors(np.delete(everything, j), start=theta, iterations=3)
        setting_error[j], label, loosest = problem.setting_error(theta_loo[j], j)
        labels.append(label)
        if loosest is not None:
            logger.warning("calibration entry %s: its known setting of %s can be checked only to +-%.3f mm (its "
                           "error model, a scan's pose error above all): a smaller misreading is not caught",
                           entries[j].name, *loosest)
    # the entry that disagrees most is named: a wrong entry also spoils the others' leave-one-out factors, so the
    # first one above the tolerance need not be it
    worst = int(np.argmax(setting_error))
    if setting_error[worst] > 0:
        raise CalibrationError(f"calibration entry {entries[worst].name}: its known setting of {labels[worst]} "
                               f"disagrees with the other entries by {setting_error[worst]:.3f} mm beyond the "
                               "tolerance (a wrong reading?)")
    for j in range(M):
        others = np.delete(everything, j)
        theta_j = theta_loo[j]
        correction_j, _, _ = problem.fit_correction(theta_j, others)
        model_j = with_correction(apply_factors(reduced, physics, theta_j, full=False), correction_j, normals)
        predicted = normal_fields(model_j, problem.settings[j][None, :])[0][0]
        seen = problem.mask[j]
        loo_residual[j] = problem.without_pose(np.array([j]), np.where(seen, problem.Y[j] - predicted, 0.0)[None])[0]
        loo[j] = float(np.sqrt(np.mean(loo_residual[j, seen] ** 2)))
        logger.info("calibration: leave-one-out %d/%d (%s): %.4f mm", j + 1, M, entries[j].name, loo[j])
    correction, kept, design = problem.fit_correction(theta, everything)
    rank = kept.shape[1]
    calibrated = with_correction(apply_factors(reduced, physics, theta), correction, normals)
    fitted = normal_fields(calibrated, problem.settings)[0]
    residual = np.sqrt(np.sum(problem.without_pose(everything, (problem.Y - fitted) * problem.mask) ** 2, axis=1)
                       / problem.mask.sum(axis=1))
    if state_range is None:
        reach = np.max(np.abs(problem.settings), axis=0)
        state_range = (-reach, reach)
    lower, upper = (np.asarray(bound, float) for bound in state_range)
    width = np.where(upper > lower, upper - lower, 1.0)
    fourth = np.where(upper > lower, (upper**5 - lower**5) / (5.0 * width), lower**4)
    variance = (lower**2 + lower * upper + upper**2) / 3.0
    discrepancy = discrepancy_modes(loo_residual, problem.settings, problem.modes, variance, fourth)
    discrepancy_noise = discrepancy_noise_modes(problem.settings, problem.modes, variance, fourth, problem.noise,
                                                loo_smoother(design), kept)
    # what the entries' noise leaves in the calibrated model at parts over the range: its correction, its factors
    states = validation_plan(lower, upper, RANGE_SAMPLES, seed=16)
    calibration_noise = np.hstack([problem.correction_spread(theta, calibrated, states),
                                   problem.factor_noise(theta, covariance, states)])
    # what leave-one-out leaves outside the smooth modes beyond the noise: not in the discrepancy, so recorded
    outside = (np.sum(loo_residual**2, axis=1) - np.sum((loo_residual @ problem.modes) ** 2, axis=1)
               - (problem.mask.sum(axis=1) - problem.modes.shape[1]) * problem.noise**2)
    rough = float(np.sqrt(max(outside.mean(), 0.0) / skin.n_nodes))
    local = local_discrepancy(loo_residual, problem.mask, problem.noise, problem.modes, skin)
    names = factor_names(reduced, physics)
    std = factor_std(covariance, theta_loo)
    calibration = Calibration(
        factors=dict(zip(names, map(float, theta), strict=True)), factor_std=dict(zip(names, map(float, std),
                                                                                      strict=True)),
        correction=correction, rank=rank, entries=problem.names, loo_rms_mm=loo,
        noise_mm=float(np.sqrt(np.mean(problem.noise**2))), residual_rms_mm=residual, setting_error_mm=setting_error,
        discrepancy=discrepancy, rough_rms_mm=rough, local_mm2=local, discrepancy_noise=discrepancy_noise,
        calibration_noise=calibration_noise)
    logger.info("calibration: correction rank %d, leave-one-out RMS %.4f mm, discrepancy rank %d RMS %.4f mm "
                "(outside the smooth modes %.4f mm)", rank, np.sqrt(np.mean(loo**2)), discrepancy.shape[1],
                np.sqrt(np.sum(discrepancy**2) / skin.n_nodes), rough)
    return calibrated, calibration


def rebuild_bases(bases: Bases, reduced: ReducedModel, calibration: str = "",
                  physics: PhysicalResponses | None = None, discrepancy: np.ndarray | None = None,
                  discrepancy_local: np.ndarray | None = None, discrepancy_noise: np.ndarray | None = None,
                  calibration_noise: np.ndarray | None = None) -> Bases:
    """Both bases rebuilt from a (calibrated) reduced model: the full-factorial ensemble by exact contact and
    superposition, then PCA and hierarchical basis with the original bases' settings. ``calibration``: the JSON record
    the new bases carry (their bases_id changes with it; the model_id stays); ``physics``: the FE model's responses
    of ``bases.reduced_model``, whose thermal response, with the calibration's change of the unit responses
    (:meth:`PhysicalResponses.thermal`), goes into the bases (the temperature term); ``discrepancy``: (N, k) mm the
    calibration's model discrepancy modes (:attr:`Calibration.discrepancy`), which the estimates' covariance and the
    within-model test then count; ``discrepancy_local``: (N,) mm^2 its rough part per node
    (:attr:`Calibration.local_mm2`), which the test's one-ring part counts; ``discrepancy_noise``,
    ``calibration_noise``: the rows' expected noise and the correction's own error (:attr:`Calibration.
    discrepancy_noise`, :attr:`Calibration.calibration_noise`). The tolerance zones (acceptance criteria on the same
    skin) are kept."""
    lower, upper = bases.pca.lower_, bases.pca.upper_
    commanded, rank = factorial_plan(lower, upper)
    logger.info("rebuilding the ensemble: %d members", len(commanded))
    ensemble = simulate_ensemble(reduced, commanded, rank, lower, upper)
    rebuilt = build_bases(ensemble, bases.skin, reduced, bases.pca.n_components, bases.pca.explained_variance,
                          bases.hierarchical.epsilon_)
    thermal = None if physics is None else physics.thermal(bases.reduced_model, reduced)
    return replace(rebuilt, calibration=calibration, thermal=thermal, physics=physics, discrepancy=discrepancy,
                   discrepancy_local=discrepancy_local, discrepancy_noise=discrepancy_noise,
                   calibration_noise=calibration_noise,
                   tolerance_zones=bases.tolerance_zones, measured_effects=bases.measured_effects)


@dataclass(frozen=True)
class ReferenceOffset:
    """A reference (a part in a known state) prepared once for many fields: what it takes off each field.

    model_id: the bases' model; offset (N,) mm: the reference read as node displacement less the model's own field at
    the reference's setting (NaN where the reference is unseen); node_std (N,) mm: the reference's node std (its error
    model, else its noise_rms, else 0); stated: whether the reference has an error model; noise_rms: its noise, mm
    (NaN: unknown)."""

    model_id: str
    offset: np.ndarray
    node_std: np.ndarray
    stated: bool
    noise_rms: float

    def relative(self, field: DisplacementField) -> DisplacementField:
        """``field`` made reference-relative: measured - offset. Unseen where either is unseen; the error model's
        node variances add (the correlation and pose of the measured field are kept; the reference's registration
        error adds as noise). CalibrationError for a field of another model or node count."""
        if field.model_id != self.model_id:
            raise CalibrationError(f"field model_id {field.model_id!r} is not the reference's {self.model_id!r}")
        values = np.asarray(field.normal_displacement, float)
        if values.shape != self.offset.shape:
            raise CalibrationError(f"field has shape {values.shape}, the reference {self.offset.shape}")
        values = values - self.offset
        n = values.size
        errors = field.errors
        if errors.kind != "none" or self.stated:
            corr = np.asarray(errors.correlation, float) if errors.kind != "none" else np.ones(n)
            errors = replace(errors, kind="stated" if errors.kind == "none" else errors.kind,
                             node_std=np.sqrt(_node_std(field, n)**2 + self.node_std**2), correlation=corr)
        noise = float(np.hypot(np.nan_to_num(field.noise_rms), np.nan_to_num(self.noise_rms)))
        return DisplacementField(model_id=field.model_id, normal_displacement=values,
                                 coverage=float(np.isfinite(values).mean()),
                                 noise_rms=noise if noise > 0 else np.nan, error_model=errors)


def reference_offset(reduced: ReducedModel, reference: DisplacementField, setting: np.ndarray,
                     reading: ReadingOfBasis | None = None) -> ReferenceOffset:
    """The reference field of a part at its known setting (P,) mm prepared for :func:`relative_field`: read as node
    displacement (a scanned reference less its slide at that setting, through the scan step's bias: the slide added
    back from the model and the bias inside the basis taken out, ``reading``: ``Bases.reading()``, needed then;
    :func:`as_node_displacement`), less the model's own field at that setting. CalibrationError for a reference of
    another model or a setting of the wrong shape."""
    if reference.model_id != reduced.model_id:
        raise CalibrationError(f"reference model_id {reference.model_id!r} is not the bases' {reduced.model_id!r}")
    setting = np.asarray(setting, dtype=float)
    if setting.shape != (len(reduced.names),):
        raise CalibrationError(f"reference setting has shape {setting.shape}, expected ({len(reduced.names)},)")
    own = solve_members(reduced, setting[None, :]).normal_displacement[0]
    gradient = None if reading is None else reading.gradient
    read = np.asarray(as_node_displacement(reference, reduced, setting, gradient, reading).normal_displacement, float)
    if read.shape != own.shape:
        raise CalibrationError(f"reference has shape {read.shape}, the bases' skin ({own.size},)")
    return ReferenceOffset(reduced.model_id, read - own, _node_std(reference, read.size),
                           reference.errors.kind != "none", float(reference.noise_rms))


def relative_field(reduced: ReducedModel, field: DisplacementField, reference: DisplacementField,
                   setting: np.ndarray, reading: ReadingOfBasis | None = None) -> DisplacementField:
    """Reference-relative field: measured - reference + the model's own field at the reference's known setting
    (P,) mm, so a static model error cancels (:func:`reference_offset`, :meth:`ReferenceOffset.relative`). The
    result is then a scan of the measured part as the estimator takes it, which takes the measured part's own slide
    and bias out."""
    return reference_offset(reduced, reference, setting, reading).relative(field)


def as_node_displacement(field: DisplacementField, reduced: ReducedModel, setting: np.ndarray,
                         gradient: SurfaceGradient | None, reading: ReadingOfBasis | None = None
                         ) -> DisplacementField:
    """A field of the part at a known setting (P,) mm as its nodes' displacement: a scanned one (error model kind
    "scan") reads the surface less its slide along itself (core.method.surface_reading), which is added back from the
    model's own displacement at that setting (``gradient``: the skin's :class:`SurfaceGradient`, needed then), and
    with ``reading`` (``Bases.reading()``) the scan step's bias inside the basis is taken out as the estimator takes
    it out of a part's scan (:meth:`ReadingOfBasis.bias_inside`); any other field is taken as it is. Calibration
    entries and references are such fields: without it the slide of their states (up to 0.003 mm RMS where the hinges
    slide the hood) would be learned as the model's discrepancy, and the bias the estimator takes out would be
    learned into the model and taken out twice."""
    if field.errors.kind != "scan":
        return field
    if gradient is None:
        raise CalibrationError("a scanned field of a known setting needs the skin's gradient (the bases' reading) "
                               "to take its slide out")
    member = solve_members(reduced, np.asarray(setting, float)[None, :])
    values = np.asarray(field.normal_displacement, float)
    added = slide(gradient, member.normal_displacement[0], member.displacement[0])
    if reading is not None:
        added = added - reading.bias_inside(values, field.errors.correlation_length_mm)
    return replace(field, normal_displacement=values + added)


def _node_std(field: DisplacementField, n: int) -> np.ndarray:
    """Per-node std (N,) mm of a field's error model; a field without one counts its noise_rms (or 0)."""
    if field.errors.kind != "none":
        return np.nan_to_num(np.asarray(field.errors.node_std, float))
    return np.full(n, float(np.nan_to_num(field.noise_rms)))


__all__ = [
    "Calibration",
    "CalibrationEntry",
    "PhysicalResponses",
    "ReferenceOffset",
    "apply_factors",
    "as_node_displacement",
    "calibrate",
    "correction_bootstrap",
    "discrepancy_modes",
    "discrepancy_noise_modes",
    "factor_names",
    "factor_std",
    "local_discrepancy",
    "loo_smoother",
    "model_physics",
    "noise_singular_values",
    "one_at_a_time",
    "rebuild_bases",
    "reference_offset",
    "relative_field",
    "truncated_fit",
    "with_correction",
]
