"""The paper's coarsening of the input field (section 5 on Table 3's 1.84 s estimate over 188,559 nodes: "This step
could be accelerated significantly by coarsening the input displacement field"): a field is estimated on a
stratified subset of the skin's nodes.

Why it loses little: the node values of a scan are correlated over the scan step's smoothing radius (at paper
resolution a node's correlation sum is about 10: some 17,000 independent samples among 180,000 seen nodes), so a
quarter of the nodes carries nearly all of the information (issue 15 run 21: the same std and coverage on 60 paper
scans). A white-noise field loses sqrt(N / n) of its precision instead, and so does a field without an error model
(its level is its own residual's): "auto" leaves those on every node (:func:`information_kept`); a stride given
coarsens them all the same. What it saves: every pass over the nodes but the reading of a scan (the weighted Grams,
the test) is divided by N / n. The within-model test's one-ring part (fields without a bias term: not scans) then
sees defects wider than the kept spacing only.

The subset: the skin's points projected on their principal plane, cut into square cells of ``stride`` node
spacings, the node nearest each cell's centre (deterministic, spread evenly, holes and outline kept). A field on it
keeps its error model with each node's correlation sum scaled to the nodes kept (:func:`restricted_errors`), and the
fit on the subset is carried back to every node through the span the estimator fits in (:class:`SpanLift`), so the
reconstruction and residual of a coarsened estimate are of the whole skin, as every consumer reads them.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING

import numpy as np

from hood_decomp.core.types import DisplacementField, FieldErrorModel
from hood_decomp.errors import BasisError

if TYPE_CHECKING:
    import scipy.sparse as sp

#: a skin with more nodes than this is coarsened when the coarsening is left to the tool ("auto") and the field's
#: errors are correlated enough (:data:`AUTO_MIN_KEPT`): the paper-resolution hood (188,730 nodes), not the built-in
#: default (its scans' correlation sums are smaller: a quarter of its nodes costs 16-20 % of std, run 20 B)
AUTO_MIN_NODES = 100_000
#: the stride "auto" takes: a quarter of the nodes (a ninth costs 6-8 % of std at paper resolution, run 20 B)
AUTO_STRIDE = 2
#: "auto" coarsens a field only where its error model keeps at least this share of the information (inverse variance)
#: on the kept nodes (:func:`information_kept`): a scan's smoothed field at paper resolution keeps all of it (g ~ 10);
#: a white one keeps a quarter (its std doubles), so it is fitted on every node
AUTO_MIN_KEPT = 0.9
#: the least number of kept nodes per column a coarsened fit and its test must estimate (the span's fields, the
#: test's smooth and rigid-body modes), so that the residual keeps three times the fitted columns' degrees of freedom:
#: fewer and the kept nodes cannot tell the fields apart (a 40-node stride on the coarse hood kept 4 nodes for 6
#: parameters and stated 1e-7 mm for errors of 1 mm)
MIN_NODES_PER_COLUMN = 4
#: the singular values of a span's rows on the kept nodes below this fraction of the largest are not lifted (their
#: fields are round-off on every node: a contact-aware span's numerical rank is 66 of 68 at 1e-10 on the paper hood)
LIFT_RCOND = 1e-10


#: :func:`information_kept` takes the median correlation sum over every this-many-th node
MEDIAN_STEP = 16


def information_kept(errors: FieldErrorModel, stride: int) -> float:
    """The share of a field's information (inverse variance of a smooth field's fit) a ``stride`` keeps, predicted
    from its error model: the median over its nodes of g / (s^2 g'), g the node's correlation sum and g' the kept
    nodes' (:func:`kept_correlation` at a fraction 1 / s^2). 1 where the correlation spans many kept nodes, 1 / s^2 for
    white noise; 0 for a field without an error model (its level comes from its own residual, whose white part a
    stride thins alike). The share grows with g, so it is taken at the median g (one value, not one per node), over
    every :data:`MEDIAN_STEP`-th node (a paper-resolution skin's median over all nodes was 2.7 ms of a scan's
    estimate, for a decision against :data:`AUTO_MIN_KEPT`)."""
    if errors.kind == "none":
        return 0.0
    correlation = np.asarray(errors.correlation, dtype=float)[::MEDIAN_STEP]
    # over the seen nodes (a finite std): a scan's unseen nodes state a correlation sum of 1, and below about half
    # coverage their 1 was the median
    correlation = correlation[np.isfinite(correlation) & np.isfinite(np.asarray(errors.node_std)[::MEDIAN_STEP])]
    if correlation.size == 0:
        return 0.0
    ratio = 1.0 / stride**2
    g = float(np.median(correlation))
    return g * ratio / float(kept_correlation(g, ratio))


def coarsening_stride(coarsen: int | str, n_nodes: int, components: str = "normal",
                      errors: FieldErrorModel | None = None) -> int:
    """The stride to use: ``coarsen`` an int >= 1 (1: every node), or "auto": :data:`AUTO_STRIDE` for a skin of more
    than :data:`AUTO_MIN_NODES` nodes fitted on its normal component, for a field whose ``errors`` keep at least
    :data:`AUTO_MIN_KEPT` of its information on the kept nodes (:func:`information_kept`; None: a field not known
    yet, taken as a scan's), else 1. Raises BasisError for anything else and for a stride > 1 with ``components``
    "xyz" (a three-component fit is not coarsened)."""
    if isinstance(coarsen, str):
        if coarsen != "auto":
            raise BasisError(f"coarsening must be 'auto' or a stride >= 1, got {coarsen!r}")
        wanted = n_nodes > AUTO_MIN_NODES and components == "normal"  # asked first: the error model costs a median
        keeps = wanted and (errors is None or information_kept(errors, AUTO_STRIDE) >= AUTO_MIN_KEPT)
        return AUTO_STRIDE if keeps else 1
    if isinstance(coarsen, bool) or not isinstance(coarsen, (int, np.integer)) or coarsen < 1:
        raise BasisError(f"coarsening stride must be an integer >= 1 or 'auto', got {coarsen!r}")
    if coarsen > 1 and components != "normal":
        raise BasisError(f"a fit of components {components!r} is not coarsened: give stride 1 or 'auto'")
    return int(coarsen)


def parse_coarsening(text: str) -> int | str:
    """A coarsening as a user writes it (``estimate --coarsen``, the estimator node's ``coarsen`` parameter): "auto"
    or an integer stride >= 1. Raises BasisError naming anything else."""
    if text == "auto":
        return text
    try:
        stride = int(text)
    except ValueError:
        stride = 0
    if stride < 1:
        raise BasisError(f"coarsening must be 'auto' or an integer stride >= 1, got {text!r}")
    return stride


def stratified_nodes(points: np.ndarray, stride: int) -> np.ndarray:
    """(n,) sorted node indices: per square cell of ``stride`` x the mean node spacing in the principal plane of
    ``points`` (N, 3) mm, the node nearest the cell's centre (every node for stride 1)."""
    points = np.asarray(points, dtype=float)
    if stride == 1:
        return np.arange(points.shape[0])
    centred = points - points.mean(axis=0)
    plane = centred @ np.linalg.svd(centred, full_matrices=False)[2][:2].T
    spacing = np.sqrt(np.ptp(plane[:, 0]) * np.ptp(plane[:, 1]) / points.shape[0])
    cell = np.floor((plane - plane.min(axis=0)) / (stride * spacing)).astype(np.int64)
    distance = np.linalg.norm(plane - ((cell + 0.5) * stride * spacing + plane.min(axis=0)), axis=1)
    key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
    order = np.lexsort((distance, key))
    first = np.r_[True, key[order][1:] != key[order][:-1]]
    return np.sort(order[first])


def kept_rings(rings: sp.csr_matrix, nodes: np.ndarray, stride: int) -> sp.csr_matrix:
    """(n, n) the one-ring incidence of the kept ``nodes`` (:func:`~.residual.ring_incidence` of the whole skin,
    ``rings`` (N, N)): each kept node with the kept nodes within ``stride`` edges, the ring on the coarser grid."""
    reach = rings[nodes]
    for _ in range(stride - 1):
        reach = reach @ rings
    reach = reach[:, nodes]
    reach.data[:] = 1.0
    return reach.tocsr()


def _lattice_sum(spacing: np.ndarray) -> np.ndarray:
    """T(a) = sum over integers k of exp(-k^2 a^2 / 2): a Gaussian correlation's sum along a line of nodes ``spacing``
    a correlation lengths apart (the square is the sum over a square lattice)."""
    k = np.arange(1, 64)
    return 1.0 + 2.0 * np.exp(-0.5 * np.multiply.outer(np.square(spacing), k**2)).sum(axis=-1)


#: spacings (correlation lengths) and their lattice sums T^2, falling from about 6e6 to 1, for inverting a correlation
#: sum to its spacing
_SPACINGS = np.geomspace(1e-3, 12.0, 600)
_SUMS = _lattice_sum(_SPACINGS) ** 2


@functools.lru_cache(maxsize=16)
def _kept_sums(ratio: float) -> np.ndarray:
    """The lattice sums T^2 at :data:`_SPACINGS` / sqrt(``ratio``): those of the kept nodes."""
    return _lattice_sum(_SPACINGS / np.sqrt(ratio)) ** 2


def kept_correlation(correlation: np.ndarray | float, ratio: float) -> np.ndarray:
    """Correlation sums on the kept nodes, a fraction ``ratio`` of a field's: each node's sum g over all nodes (>= 1)
    read as the lattice sum of a Gaussian correlation, T(a)^2 = g with a the node spacing in correlation lengths, and
    the kept nodes' sum T(a / sqrt(ratio))^2 at their wider spacing (interpolated in g). It is g x ratio where the
    correlation spans many kept nodes and 1 where it spans none (a white field; a stride wider than the smoothing):
    on a coarse-hood field smoothed by three one-ring passes (g = 20) a quarter keeps 5.0 and a ninth 2.2, as the
    estimates' spread shows, where 1 + (g - 1) x ratio (5.8, 3.1) over-stated their std by 7 and 20 %."""
    g = np.maximum(np.asarray(correlation, dtype=float), 1.0)
    if not np.any(g > 1.0):  # white noise (a stated level): nothing to thin, and the interpolation costs 0.3 ms
        return g
    return np.interp(g, _SUMS[::-1], _kept_sums(float(ratio))[::-1])


def restricted_errors(errors: FieldErrorModel, nodes: np.ndarray, n_nodes: int) -> FieldErrorModel:
    """``errors`` of a field of ``n_nodes`` nodes, on the kept ``nodes``: their std and view weights, and each
    correlation sum of the kept nodes (:func:`kept_correlation`; the same for the making's bias correlation); the
    pose as it is. A model without node values ("none") is returned as it is."""
    if errors.kind == "none":
        return errors
    ratio = nodes.size / n_nodes
    views = tuple(dataclasses.replace(view, weight=np.asarray(view.weight)[nodes]) for view in errors.view_poses)
    bias = float(kept_correlation(errors.bias_correlation, ratio)) if errors.bias_correlation > 0 else 0.0
    return dataclasses.replace(errors, node_std=np.asarray(errors.node_std)[nodes],
                               correlation=kept_correlation(np.asarray(errors.correlation)[nodes], ratio),
                               bias_correlation=bias, view_poses=views)


def restricted_field(field: DisplacementField, nodes: np.ndarray) -> DisplacementField:
    """``field`` (N node values) on the kept ``nodes`` (module docstring), its error model restricted alike
    (:func:`restricted_errors`); its 3D displacement is not kept (a coarsened fit is of the normal component)."""
    values = np.asarray(field.normal_displacement, dtype=float)
    return DisplacementField(field.model_id, values[nodes], field.coverage, field.noise_rms,
                             restricted_errors(field.errors, nodes, values.shape[0]))


@dataclasses.dataclass(frozen=True)
class SpanLift:
    """The coefficients x of a span's field from its values on the kept nodes: the span's rows there A (n, k), x =
    A^+ v with singular values below :data:`LIFT_RCOND` of the largest left out; the field on every node is then
    the whole skin's rows times x. pinv: (k, n)."""

    pinv: np.ndarray

    @classmethod
    def of(cls, rows: np.ndarray) -> SpanLift:
        """The lift of the span with rows ``rows`` (n, k) on the kept nodes."""
        return cls(np.linalg.pinv(np.asarray(rows, dtype=float), rcond=LIFT_RCOND))

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """(k,) the coefficients of the span's field whose values on the kept nodes are ``values`` (n,)."""
        return self.pinv @ values
