"""The prepared scan skin of a set of bases, with the scan step's own bias measured on the part's own fields.

The scan step smooths; on a curved displacement that biases the node values (the kernel's second moment times the
displacement's curvature, one-sided fits at free edges), and the within-model test allows for it from each residual's
rough excess (at least ``FieldErrorModel.bias_variance_floor``) times a correlation sum
(``FieldErrorModel.bias_correlation``, core.method.residual.split_level). How large both are depends on the skin, the
kernel and what the part's displacements look like, so they are measured once per prepared skin: the FE model's states
spread over the declared ranges, scanned noise-free through the scan step's own field path
(:meth:`ScanFieldEstimator.surface_samples`), minus what a scan reads of each state (its normal displacement less its
slide along the surface, which the estimator takes out: core.method.surface_reading), split by the test's own
arithmetic (:func:`~hood_decomp.core.method.residual.bias_split`). Issue 15 runs 13 and 17 (benchmarks/RESULTS.md)
check them against noise-free synthetic scans of other FE states.

The bias' part inside the PCA basis is not allowed for but taken out by the estimator (core.method.surface_reading
ReadingOfBasis): :func:`reading_bias` measures what each basis field reads in excess, by the same noise-free path.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from collections.abc import Iterable

import numpy as np

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.method.bases import Bases
from hood_decomp.core.method.residual import DEFAULT_SMOOTH_DEGREE, bias_split, smooth_modes
from hood_decomp.core.method.surface_reading import ScanReadingBias, SurfaceGradient, slide
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, prepared_estimator
from hood_decomp.core.types import FieldErrorModel
from hood_decomp.errors import BasisError

logger = logging.getLogger(__name__)

#: states of the FE model the bias is measured on (uniform over the declared ranges, a fixed seed: the same bases
#: give the same prepared skin)
BIAS_STATES = 24
BIAS_SEED = 20261125


def state_bias(estimator: ScanFieldEstimator, gradient: SurfaceGradient, displacement: np.ndarray
               ) -> tuple[np.ndarray, FieldErrorModel]:
    """The scan step's bias on one state of the part, displaced by ``displacement`` (N, 3) mm: a noise-free scan of
    it (:meth:`ScanFieldEstimator.surface_samples`, the Jacobian from ``gradient`` of the skin) through
    ``estimator``'s field path without its outlier pass (on a noise-free cloud it would drop the curvature's own
    residuals), minus what a scan reads of the state (its normal displacement less its slide, which the estimator
    takes out): (N,) mm, NaN where unseen; and that field's error model per unit point noise."""
    noise_free = copy.copy(estimator)
    noise_free.outlier_sigma = np.inf
    normal = np.sum(displacement * gradient.normals, axis=1)
    jacobian = np.stack([gradient(displacement[:, c]) for c in range(3)], axis=1)
    field = noise_free.field(noise_free.surface_samples(displacement, jacobian))
    errors = field.error_model
    unit = dataclasses.replace(errors, node_std=errors.node_std / max(field.noise_rms, 1e-300))
    return field.normal_displacement - (normal - slide(gradient, normal, displacement)), unit


def scan_bias(estimator: ScanFieldEstimator, bases: Bases, count: int = BIAS_STATES, seed: int = BIAS_SEED
              ) -> tuple[np.ndarray, FieldErrorModel] | None:
    """:func:`state_bias` (N, count) mm of ``count`` states drawn uniformly over the bases' declared ranges, solved
    by the bases' reduced FE model (exact contact), and the error model of the last; None for bases without a
    reduced model."""
    if bases.reduced_model is None:
        return None
    rng = np.random.default_rng(seed)
    states = rng.uniform(bases.pca.lower_, bases.pca.upper_, size=(count, len(bases.pca.lower_)))
    return _biases(estimator, bases, solve_members(bases.reduced_model, states).displacement)


def _biases(estimator: ScanFieldEstimator, bases: Bases, displacements: Iterable[np.ndarray]
            ) -> tuple[np.ndarray, FieldErrorModel]:
    """:func:`state_bias` of each displacement (N, 3) mm of ``bases``' part: (N, k) mm, and the error model of the
    last."""
    gradient = bases.reading().gradient  # the estimator's own, fitted once per bases
    biases = [state_bias(estimator, gradient, np.asarray(moved, float)) for moved in displacements]
    return np.column_stack([bias for bias, _ in biases]), biases[-1][1]


def measured_bias(estimator: ScanFieldEstimator, bases: Bases) -> dict[str, np.ndarray]:
    """The scan bias of ``estimator`` (fitted to ``bases.skin``) on the part of ``bases``, as prepared skin arrays:
    :func:`bias_split` of :func:`scan_bias` outside the PCA basis, ``bias_correlation`` (1,) nodes and
    ``bias_variance_floor`` (1,) mm^2 per node. Empty for bases without a reduced model (the scan step then states
    its area fallback, ``SMOOTHING_BIAS_AREA_MM2``, and no floor)."""
    measured = scan_bias(estimator, bases)
    if measured is None:
        return {}
    bias, errors = measured
    modes = smooth_modes(np.asarray(bases.skin.points, float), DEFAULT_SMOOTH_DEGREE)
    correlation, floor = bias_split(bias, bases.pca.components_.T, errors, modes)
    logger.info("scan bias measured on %d states: correlation %.1f nodes (area fallback %.1f), level %.3g mm^2 "
                "per node", bias.shape[1], correlation, estimator.bias_correlation_, floor)
    return {"bias_correlation": np.array([correlation]), "bias_variance_floor": np.array([floor])}


def reading_bias(estimator: ScanFieldEstimator, bases: Bases) -> ScanReadingBias | None:
    """The scan step's reading bias of ``bases``' PCA fields (:class:`ScanReadingBias`): :func:`state_bias` of the
    basis' mean 3D field and of each basis field's 3D field (one noise-free scan each, through ``estimator``, fitted
    to ``bases.skin``; 11 scans, 0.8 s on the default hood), unseen nodes 0 (no scan sees them). None, with a
    warning, where it is too large to be taken out by one step (ScanReadingBias.validate: a skin too coarse for the
    kernel, e.g. the tests' toy skins); the within-model test's allowance then stands for all of it."""
    biases = np.nan_to_num(_biases(estimator, bases, [bases.pca.mean_field_3d_, *bases.pca.components_3d_])[0].T)
    measured = ScanReadingBias(float(estimator.radius_mm_), biases[0], biases[1:])
    try:
        measured.validate(bases.pca)
    except BasisError as error:
        logger.warning("the scan reading bias of the basis is not taken out: %s", error)
        return None
    logger.info("scan reading bias of %d basis fields: RMS %.2e mm (mean field)", len(biases) - 1,
                float(np.sqrt(np.mean(biases[0] ** 2))))
    return measured


def with_reading_bias(bases: Bases, estimator: ScanFieldEstimator | None = None) -> Bases:
    """``bases`` as a bases file written with its scan skin holds them: with their :func:`reading_bias` measured
    through ``estimator`` (default: the default scan options' estimator of their skin, :func:`prepared_estimator`, a
    stored preparation where one is registered) unless they carry one. For bases built or rebuilt in memory (a
    calibration, close-loop's added effect) that read scans as a loaded file does, and for older files read before a
    calibration."""
    if bases.scan_reading_bias is not None:
        return bases
    estimator = prepared_estimator(bases.skin) if estimator is None else estimator
    return dataclasses.replace(bases, scan_reading_bias=reading_bias(estimator, bases))


def scan_ready(bases: Bases) -> tuple[Bases, dict[str, np.ndarray]]:
    """``bases`` with their :func:`reading_bias` measured (unless they carry one) and their
    :func:`prepared_scan_skin`, through one estimator of the default scan options: what a bases file written with its
    scan skin holds (io.bases.save_bases)."""
    estimator = ScanFieldEstimator().fit(bases.skin)
    ready = with_reading_bias(bases, estimator)
    return ready, prepared_scan_skin(ready, estimator)


def prepared_scan_skin(bases: Bases, estimator: ScanFieldEstimator | None = None) -> dict[str, np.ndarray]:
    """The prepared skin (:meth:`ScanFieldEstimator.prepared_skin` arrays) of ``bases.skin`` for the default scan
    options, with ``bias_correlation`` and ``bias_variance_floor`` measured (:func:`measured_bias`) where the bases
    can; what a bases file stores (io.bases) and what ``ScanFieldEstimator().fit(skin, prepared=...)`` takes.
    estimator: one already fitted to the skin (its grid and kernel are reused)."""
    estimator = ScanFieldEstimator().fit(bases.skin) if estimator is None else estimator
    arrays = estimator.prepared_skin()
    return arrays | measured_bias(estimator, bases)
