"""The prepared scan skin of a set of bases, with the scan step's smoothing bias measured on the part's own fields.

The scan step smooths; on a curved displacement that biases the node values (the kernel's second moment times the
displacement's curvature), and the within-model test allows for it from each residual's rough excess times a
correlation sum (``FieldErrorModel.bias_correlation``, core.method.residual.split_level). How large that sum is
depends on the skin, the kernel and what the part's displacements look like, so it is measured once per prepared
skin: the FE model's fields at states spread over the declared ranges, through the scan step's own smoother
(:meth:`ScanFieldEstimator.smoothing_bias`), split by the test's own arithmetic
(:func:`~hood_decomp.core.method.residual.bias_correlation_of`). Issue 15 run 10 (benchmarks/RESULTS.md) checks it
against noise-free synthetic scans of FE states.
"""

from __future__ import annotations

import logging

import numpy as np

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.core.method.bases import Bases
from hood_decomp.core.method.residual import DEFAULT_SMOOTH_DEGREE, bias_correlation_of, smooth_modes
from hood_decomp.core.scan.scan_field import ScanFieldEstimator

logger = logging.getLogger(__name__)

#: states of the FE model the bias is measured on (uniform over the declared ranges, a fixed seed: the same bases
#: give the same prepared skin)
BIAS_STATES = 24
BIAS_SEED = 20261125


def bias_fields(bases: Bases, count: int = BIAS_STATES, seed: int = BIAS_SEED
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """The part at ``count`` states drawn uniformly over the bases' declared ranges, solved by the bases' reduced FE
    model (exact contact): normal displacement (N, count) mm and in-plane displacement (N, count, 3) mm; None for
    bases without a reduced model."""
    if bases.reduced_model is None:
        return None
    rng = np.random.default_rng(seed)
    states = rng.uniform(bases.pca.lower_, bases.pca.upper_, size=(count, len(bases.pca.lower_)))
    members = solve_members(bases.reduced_model, states)
    normals = np.asarray(bases.skin.normals, float)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    moved = np.asarray(members.displacement, float)  # (count, N, 3)
    normal = np.einsum("knd,nd->kn", moved, normals)
    return normal.T, np.transpose(moved - normal[..., None] * normals, (1, 0, 2))


def measured_bias_correlation(estimator: ScanFieldEstimator, bases: Bases) -> float | None:
    """The bias correlation sum (nodes) of ``estimator`` (fitted to ``bases.skin``) on the part of ``bases``:
    :func:`bias_correlation_of` of the scan step's bias on :func:`bias_fields` (its smoothing and the surface slid
    along itself, :meth:`ScanFieldEstimator.smoothing_bias`) outside the PCA basis, with the error model of the same
    smoother. None for bases without a reduced model (the scan step then states its area fallback,
    ``SMOOTHING_BIAS_AREA_MM2``)."""
    fields = bias_fields(bases)
    if fields is None:
        return None
    bias, errors = estimator.smoothing_bias(*fields)
    modes = smooth_modes(np.asarray(bases.skin.points, float), DEFAULT_SMOOTH_DEGREE)
    value = bias_correlation_of(bias, bases.pca.components_.T, errors, modes)
    logger.info("smoothing bias correlation measured on %d states: %.1f nodes (area fallback %.1f)",
                bias.shape[1], value, estimator.bias_correlation_)
    return value


def prepared_scan_skin(bases: Bases, estimator: ScanFieldEstimator | None = None) -> dict[str, np.ndarray]:
    """The prepared skin (:meth:`ScanFieldEstimator.prepared_skin` arrays) of ``bases.skin`` for the default scan
    options, with ``bias_correlation`` measured (:func:`measured_bias_correlation`) where the bases can; what a bases
    file stores (io.bases) and what ``ScanFieldEstimator().fit(skin, prepared=...)`` takes. estimator: one already
    fitted to the skin (its grid and kernel are reused)."""
    estimator = ScanFieldEstimator().fit(bases.skin) if estimator is None else estimator
    arrays = estimator.prepared_skin()
    value = measured_bias_correlation(estimator, bases)
    if value is not None:
        arrays["bias_correlation"] = np.array([value])
    return arrays
