"""From a scan to the signed normal displacement of every visible skin node (paper section 3, input; section 4.3.3).

The paper measures the distance between a scan and the simulation mesh with CloudCompare's cloud-to-mesh distance and
multiplies it by the node normals. Here the same quantity is computed directly per node, on an open surface, with
smoothing and a validity mask:

1. Every scan point (already registered into the part frame) is assigned to a nearby skin node j through a lookup
   grid, and its signed distance to the *nominal* skin is measured along n_j against a quadric fitted to the nominal
   nodes around j: d = (p - x_j).n_j - q_j(u, v). The sign comes from the node normal, never from ray parity: the
   skin is an open surface and has no inside.
2. Per node i, d is fitted by a weighted plane d(u, v) = a + b_u u + b_v v in node i's tangent coordinates over the
   scan points within ``radius_mm`` (biweight kernel on the node-to-node distance). The intercept a is the node's
   signed normal displacement: the nominal normal line intersected with the locally fitted scanned surface. Because
   only the (smooth) difference to the nominal is fitted, a plane suffices even on a curved part, and a one-sided
   neighbourhood at a free edge is extrapolated without bias; there the radius is widened (``edge_widening``) to
   make up for the missing half of the points.
3. A second pass drops points whose residual exceeds ``outlier_sigma`` robust standard deviations (outliers, mixed
   pixels) and refits. The residual RMS of the inliers is the scan-noise estimate (along the normal).
4. A node without support is NaN, never zero: too few points, its support all on one side far away (intercept
   variance inflated more than ``max_inflation`` times), or no points within half the radius (a gap in the scan).

Speed: all per-point work is vectorised (and threaded per core for large scans); the per-node fits are built from
per-node moment sums (``np.bincount``) mixed by a sparse node-to-node kernel, so no per-node neighbour search over the
scan is needed.
Units: mm throughout. Node order: the skin's.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hood_decomp.core.scan import kernels
from hood_decomp.core.scan.registration import RegistrationResult, register_scan
from hood_decomp.core.types import DisplacementField, FieldErrorModel, SkinSurface
from hood_decomp.errors import ScanError

if TYPE_CHECKING:  # scipy is imported where used (0.16 s since scipy 1.17): --help does not pay it
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

logger = logging.getLogger(__name__)

# A lookup grid finer than this many cells would cost more memory than it saves time.
_MAX_GRID_CELLS = 12_000_000
# Cells per edge of the lookup table's bricks, across the axis the skin's normals mostly point along (that axis is
# not bricked): a 64-byte line of the int32 table then holds a 4 x 4 patch of one layer of cells, which a sheet
# crosses whole, not 16 cells of one column, of which it crosses one or two. Paper skin, one thread (benchmarks/
# RESULTS.md, issue 19, 2026-11-25): the locate pass 4 ms faster at 1M points, as fast at 10M.
GRID_BRICK = 4
# Scans larger than this many points per core are located in parallel threads.
_CHUNK_POINTS = 200_000
# Nominal nodes used for each node's quadric (the node itself included).
_QUADRIC_NEIGHBOURS = 13
# The FALLBACK for a skin prepared without its part's fields (no bases, or bases without a reduced model): a skin
# prepared with its bases stores the bias correlation measured on the part's own FE states (core/loop/scan_skin.py,
# ``bias_correlation`` of PREPARED_SKIN; issue 15 run 13, the surface's slide taken out by the estimator: coarse 22,
# default 45 nodes, where this area gives 157 and 1,000). How far the smoothing bias is correlated, as an area of the
# skin (mm^2). As a node count (1000, tuned on the default hood's 59 mm^2 nodes) it stood for 6.4 times the area on
# the coarse hood's 375 mm^2 nodes (issue 15 run 5). Set where the within-model test's false-alarm rate on 120
# default scans came down (300 nodes: 12.5 %; 1000 nodes: none).
SMOOTHING_BIAS_AREA_MM2 = 59_000.0
# Twicing by default only at smoothing radii above this (mm). The bias grows as the radius squared times the
# displacement's curvature (a property of the part, not of the mesh): 0.009-0.011 mm RMS at the coarse hood's 50 mm,
# 0.002-0.0027 mm at the default hood's 19 mm, so about 0.0004 mm at the paper mesh's 7.8 mm, the level of the
# nominal geometry's own floor; there twicing would only add node noise and a fourth of the per-scan time.
TWICING_MIN_RADIUS_MM = 12.0
# Kernel weight of a node within half the radius (biweight (1 - 0.5^2)^2): a node needs scan points this close, or it
# sits in a gap of the scan and a value there would be interpolated across the gap rather than measured.
_NEAR_WEIGHT = 0.75**2


def smoothing_bias_correlation(skin: SkinSurface) -> float:
    """The scan step's smoothing bias on ``skin`` as a correlation sum in nodes (``FieldErrorModel.bias_correlation``)
    where none was measured for it: :data:`SMOOTHING_BIAS_AREA_MM2` over the skin's area per node (mm^2 from its
    (T, 3) triangles)."""
    return SMOOTHING_BIAS_AREA_MM2 * skin.n_nodes / max(float(np.sum(skin.triangle_areas())), 1e-300)


#: The prepared skin's arrays (ScanFieldEstimator.prepared_skin): named dimensions (N nodes, N1 = N + 1, G grid cells,
#: Z kernel entries; digits fixed) and kind.
PREPARED_SKIN: dict[str, tuple[tuple[str, ...], str]] = {
    "spacing": (("1",), "float"), "radius": (("1",), "float"), "gate2": (("N",), "float"),
    "quadric": (("N", "5"), "float"), "node_radius": (("N",), "float"), "grid_origin": (("3",), "float"),
    "grid_cell": (("1",), "float"), "grid_shape": (("3",), "integer"), "grid_table": (("G",), "integer"),
    "grid_brick": (("3",), "integer"),
    "kernel_indptr": (("N1",), "integer"), "kernel_indices": (("Z",), "integer"), "kernel_data": (("Z",), "float"),
    "twicing_variance": (("N",), "float"), "bias_correlation": (("1",), "float"),
    "bias_variance_floor": (("1",), "float"),
}  # fmt: skip
#: arrays of PREPARED_SKIN a prepared skin may lack: made at the first scan that needs them (files written before);
#: ``bias_correlation`` and ``bias_variance_floor`` are measured from the part's own fields (core.loop.scan_skin),
#: without them the area fallback and no floor;
#: without ``grid_brick`` (written before issue 19, session 12) ``grid_table`` is in plain C order, laid out
#: in bricks when the skin is fitted
PREPARED_OPTIONAL = frozenset({"twicing_variance", "bias_correlation", "bias_variance_floor", "grid_brick"})


@dataclass(frozen=True)
class PointDistances:
    """Per scan point: signed distance to the nominal skin and where it landed.

    distance: (M,) mm, signed along the normal of ``node`` (positive on the normal's side); NaN where the point is off
        the skin (outside the lookup grid, beyond a free edge or farther than ``max_distance_mm``).
    node: (M,) int64, the skin node the point was assigned to (a node within about one mesh spacing of the nearest);
        -1 where off the skin.
    tangent: (M, 2) mm, the point's tangent coordinates in that node's frame.
    """

    distance: np.ndarray
    node: np.ndarray
    tangent: np.ndarray


def _unique_edges(triangles: np.ndarray, n: int) -> np.ndarray:
    """(E, 2) node pairs (low, high) of the triangles' (T, 3) edges, each once, in row-major order. A sparse matrix
    of the half-edges sums the duplicates by a counting sort over rows (np.unique(axis=0) sorts rows of pairs,
    about 15 times slower at 1.1M half-edges)."""
    import scipy.sparse as sp

    a, b = triangles.ravel(), np.roll(triangles, -1, axis=1).ravel()
    pairs = sp.csr_matrix((np.ones(a.size, np.int32), (np.minimum(a, b), np.maximum(a, b))), shape=(n, n)).tocoo()
    return np.column_stack([pairs.row, pairs.col]).astype(np.int64)


def _row_blocks(kernel: sp.csr_matrix, parts: int) -> list[tuple[slice, sp.csr_matrix]]:
    """The (N, N) CSR ``kernel`` as the blocks of consecutive rows of :func:`kernels.row_parts`, each a CSR matrix over
    the kernel's own arrays (no copy), with the rows it covers."""
    import scipy.sparse as sp

    indptr = kernel.indptr
    return [(slice(start, stop), sp.csr_matrix((kernel.data[indptr[start]:indptr[stop]],
                                                kernel.indices[indptr[start]:indptr[stop]],
                                                indptr[start : stop + 1] - indptr[start]),
                                               shape=(stop - start, kernel.shape[1])))
            for start, stop in kernels.row_parts(indptr, parts)]


def _check_prepared(prepared: Mapping[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """The arrays of a prepared skin for a skin of ``n`` nodes, checked (shapes, kinds, finiteness, index ranges);
    raises ScanError naming the first problem."""
    missing = sorted(set(PREPARED_SKIN) - PREPARED_OPTIONAL - set(prepared))
    if missing:
        raise ScanError(f"prepared skin lacks {', '.join(missing)}")
    arrays = {name: np.asarray(prepared[name]) for name in PREPARED_SKIN if name in prepared}
    sizes = {"N": n, "N1": n + 1, "G": int(np.prod(arrays["grid_shape"])) if arrays["grid_shape"].size == 3 else -1,
             "Z": arrays["kernel_indices"].size}  # fmt: skip
    for name, (dims, kind) in PREPARED_SKIN.items():
        if name not in arrays:
            continue
        array = arrays[name]
        expected = tuple(int(d) if d.isdigit() else sizes[d] for d in dims)
        if array.shape != expected:
            raise ScanError(f"prepared skin {name} has shape {array.shape}, expected {expected} ({', '.join(dims)})")
        if kind == "integer" and array.dtype.kind not in "iu":
            raise ScanError(f"prepared skin {name} holds {array.dtype}, expected integers")
        if kind == "float" and not np.all(np.isfinite(array)):
            raise ScanError(f"prepared skin {name} holds non-finite values")
    positive = ("spacing", "radius", "grid_cell", "node_radius", "grid_shape", "twicing_variance", "bias_correlation",
                "grid_brick")
    bad = [name for name in positive if name in arrays and np.any(arrays[name] <= 0)]
    brick = arrays.get("grid_brick")  # powers of two, whole bricks
    if brick is not None and (np.any(brick & (brick - 1)) or np.any(arrays["grid_shape"] % np.maximum(brick, 1))):
        bad.append("grid_brick")
    bad += [name for name in ("gate2", "bias_variance_floor") if name in arrays and np.any(arrays[name] < 0)]
    if np.any(arrays["kernel_data"] < 0) or np.any(arrays["kernel_data"] > 1):  # biweight values
        bad.append("kernel_data")
    indptr, indices, table = arrays["kernel_indptr"], arrays["kernel_indices"], arrays["grid_table"]
    if indptr[0] != 0 or indptr[-1] != indices.size or np.any(np.diff(indptr) < 0):
        bad.append("kernel_indptr")
    for name, values in (("kernel_indices", indices), ("grid_table", table)):
        if values.size and (values.min() < 0 or values.max() >= n):
            bad.append(name)
    if bad:
        raise ScanError(f"prepared skin for {n} nodes has out-of-range {', '.join(bad)}")
    return arrays


def _tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) completing each normal to a right-handed frame (t1, t2, n)."""
    helper = np.zeros_like(normals)
    use_x = np.abs(normals[:, 0]) < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(normals, t1)


class ScanFieldEstimator:
    """Signed normal displacement per visible skin node from scan points in the part frame.

    ``fit(skin)`` prepares the nominal skin once (node frames, nominal quadrics, lookup grid, node kernel); then
    ``field(points_mm)`` turns a registered scan into a :class:`DisplacementField` and ``point_distances(points_mm)``
    gives the per-point signed distances to the nominal skin (the quantity CloudCompare's cloud-to-mesh distance
    computes).

    radius_mm: smoothing radius of the per-node plane fit; None = 2.5 x the median mesh edge length.
    max_distance_mm: points farther than this from the nominal skin are not part of it (background, gross outliers).
    min_points: minimum weighted number of scan points supporting a node (and a quarter of it, at least 1, within half
        the radius).
    max_inflation: maximum variance inflation of the intercept by a one-sided support (a half disk at a free edge
        gives about 3.5; a node beyond the border of the scanned area gives more).
    outlier_sigma: residual threshold of the second pass, in robust standard deviations.
    edge_widening: factor on the radius at a straight free edge (one-sided neighbourhood); a corner gets up to 1.5
        times the extra.
    twicing: add the same fit of the points' residuals (:meth:`_twice`): removes most of the smoothing's bias on a
        curved displacement at the cost of some node noise (the error model states both); None: where the radius
        exceeds ``TWICING_MIN_RADIUS_MM``.
    """

    def __init__(
        self,
        radius_mm: float | None = None,
        max_distance_mm: float = 5.0,
        min_points: float = 8.0,
        max_inflation: float = 8.0,
        outlier_sigma: float = 4.0,
        edge_widening: float = 2.0,
        twicing: bool | None = None,
    ) -> None:
        self.radius_mm = radius_mm
        self.max_distance_mm = max_distance_mm
        self.min_points = min_points
        self.max_inflation = max_inflation
        self.outlier_sigma = outlier_sigma
        self.edge_widening = edge_widening
        self.twicing = twicing

    # ------------------------------------------------------------------------------------------------ preparation
    def fit(self, skin: SkinSurface, prepared: Mapping[str, np.ndarray] | None = None) -> ScanFieldEstimator:
        """Prepare the nominal skin: (N, 3) points and unit normals, (T, 3) triangles, mm.

        prepared: the arrays of :meth:`prepared_skin` of an estimator with the same options fitted to this skin (as
        stored in a bases file): the lookup grid, quadrics, gates and kernel are then taken from it, not rebuilt.
        """
        points = np.asarray(skin.points, dtype=np.float64)
        normals = np.asarray(skin.normals, dtype=np.float64)
        n = points.shape[0]
        if points.ndim != 2 or points.shape[1] != 3 or n < 4 or normals.shape != points.shape:
            raise ScanError(f"skin must have (N>=4, 3) points and normals; got {points.shape} and {normals.shape}")
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        if prepared is None:
            edges = _unique_edges(np.asarray(skin.triangles, dtype=np.int64), n)
            edge_length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
            spacing = float(np.median(edge_length))
            longest = np.zeros(n)
            np.maximum.at(longest, edges[:, 0], edge_length)
            np.maximum.at(longest, edges[:, 1], edge_length)
        else:
            prepared = _check_prepared(prepared, n)
            spacing = float(prepared["spacing"][0])

        self.skin_ = skin
        self.spacing_mm_ = spacing
        self.radius_mm_ = float(self.radius_mm) if self.radius_mm is not None else 2.5 * spacing
        self.twicing_ = self.radius_mm_ > TWICING_MIN_RADIUS_MM if self.twicing is None else bool(self.twicing)
        self.center_ = points.mean(axis=0)
        self.skin_size_mm_ = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))  # bounding-box diagonal
        measured = prepared is not None and "bias_correlation" in prepared
        self.bias_measured_ = measured
        self.bias_correlation_ = (float(prepared["bias_correlation"][0]) if measured
                                  else smoothing_bias_correlation(skin))
        floored = measured and "bias_variance_floor" in prepared
        self.bias_variance_floor_ = float(prepared["bias_variance_floor"][0]) if floored else 0.0
        self.points_ = points
        tangent1, tangent2 = _tangent_frames(normals)
        self.frames_ = np.stack([tangent1, tangent2, normals], axis=1)  # (N, 3, 3) rows t1, t2, n
        self._prepare_moment_maps(points - self.center_, tangent1, tangent2)
        # A point belongs to node j when it lies within this tangential distance (grid lookups may be off by about
        # one spacing, hence the generous factor); beyond it, it is past a free edge. So a point on the surface's
        # own continuation up to about 2.5 spacings past a free edge still counts as skin.
        if prepared is None:
            self.gate2_ = (1.6 * longest + 0.5 * spacing) ** 2
            from scipy.spatial import cKDTree  # preparing a skin only

            tree = cKDTree(points)
            self.quadric_ = self._fit_quadrics(tree)
            self._build_grid()
            self.kernel_ = self._build_kernel(tree)
        else:
            if abs(float(prepared["radius"][0]) - self.radius_mm_) > 1e-9 * self.radius_mm_:
                raise ScanError(f"prepared skin has radius {float(prepared['radius'][0])} mm; this estimator uses "
                                f"{self.radius_mm_} mm")
            self.gate2_, self.quadric_ = prepared["gate2"], prepared["quadric"]
            self._set_grid(prepared["grid_origin"], float(prepared["grid_cell"][0]), prepared["grid_shape"],
                           prepared["grid_table"], prepared.get("grid_brick"))  # fmt: skip
            self.node_radius_mm_ = prepared["node_radius"]
            if self.twicing_ and "twicing_variance" in prepared:
                self.twicing_variance_ = prepared["twicing_variance"]
            import scipy.sparse as sp

            kernel = (prepared["kernel_data"], prepared["kernel_indices"], prepared["kernel_indptr"])
            self.kernel_ = sp.csr_matrix(kernel, shape=(n, n))
        self.kernel_blocks_ = _row_blocks(self.kernel_, kernels.threads())
        # What a located point reads of its node, in one row: position in grid units, frame, quadric, squared gate.
        grid_position = (points - self.grid_origin_) / self.grid_cell_mm_
        self.node_table_ = np.column_stack([grid_position, self.frames_.reshape(n, 9), self.quadric_, self.gate2_])
        return self

    def _prepare_moment_maps(self, x: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> None:
        """Per-node maps from cell sums to raw 3D moments about the centroid, and back to tangent frames.

        A point of cell j sits at x_j + u t1_j + v t2_j (x_j about the centroid), so its first moments are
        [1, u, v] @ [x_j; t1_j; t2_j] and its second moments [1, u, v, uu, uv, vv] @ (6 x 6 map) in upper-triangle
        order; for node i, the tangent quadratic forms t_a^T S t_b of a moment matrix S are (3 x 6 map) @ S. Both
        maps are products of the basis rows [x_j; t1_j; t2_j] (N, 3, 3), which is all that is kept: the kernels build
        them per node as they go (kernels._sym), not as (N, 6, 6) and (N, 3, 6) arrays (81 MB at paper resolution).
        """
        self.moment_basis_ = np.stack([x, t1, t2], axis=1)  # (N, 3, 3)
        self.t1_dot_x_ = np.einsum("nd,nd->n", t1, x)
        self.t2_dot_x_ = np.einsum("nd,nd->n", t2, x)

    def _fit_quadrics(self, tree: cKDTree) -> np.ndarray:
        """(N, 5) coefficients of z = c0 u + c1 v + c2 u^2 + c3 u v + c4 v^2 (u, v, z in node frame, mm)."""
        k = min(_QUADRIC_NEIGHBOURS, self.points_.shape[0])
        _, neighbours = tree.query(self.points_, k=k, workers=-1)
        rel = self.points_[neighbours] - self.points_[:, None, :]
        u, v, z = (np.einsum("nkd,nd->nk", rel, self.frames_[:, axis]) for axis in range(3))
        u, v = u / self.spacing_mm_, v / self.spacing_mm_
        design = np.stack([u, v, u * u, u * v, v * v], axis=2)
        normal_matrix = np.einsum("nki,nkj->nij", design, design) + 1e-9 * np.eye(5)
        coef = np.linalg.solve(normal_matrix, np.einsum("nki,nk->ni", design, z)[..., None])[..., 0]
        scale = np.array([1, 1, 1 / self.spacing_mm_, 1 / self.spacing_mm_, 1 / self.spacing_mm_]) / self.spacing_mm_
        return coef * scale

    def _build_grid(self) -> None:
        """A dense lookup grid: every cell holds the skin node nearest to it (exact on the node cells, EDT between)."""
        # Wider than any gate: a point clamped onto a border cell is then always dropped by the gates.
        margin = self.max_distance_mm + float(np.sqrt(self.gate2_.max())) + 2.0 * self.spacing_mm_
        lo = self.points_.min(axis=0) - margin
        extent = self.points_.max(axis=0) + margin - lo
        brick = self._grid_brick()
        cell = self.spacing_mm_
        while np.prod(-(-np.ceil(extent / cell) // brick) * brick) > _MAX_GRID_CELLS:
            cell *= 1.25
        shape = (-(-np.ceil(extent / cell) // brick) * brick).astype(np.int64)  # whole bricks
        keys = np.floor((self.points_ - lo) / cell).astype(np.int64)
        table = np.full(tuple(shape), -1, dtype=np.int64)
        table[keys[:, 0], keys[:, 1], keys[:, 2]] = np.arange(self.points_.shape[0])
        from scipy import ndimage  # preparing a skin only (a stored one needs none of it)

        nearest = ndimage.distance_transform_edt(table < 0, return_distances=False, return_indices=True)
        plain = table[tuple(nearest)].astype(np.int32)
        self._set_grid(lo, float(cell), shape, kernels.brick_order(plain, brick), brick)

    def _grid_brick(self) -> np.ndarray:
        """(3,) cells per axis of the lookup table's bricks: ``GRID_BRICK`` but 1 along the axis the skin's normals
        mostly point along."""
        brick = np.full(3, GRID_BRICK, dtype=np.int64)
        brick[int(np.argmax(np.abs(self.frames_[:, 2]).sum(axis=0)))] = 1
        return brick

    def _set_grid(self, origin: np.ndarray, cell_mm: float, shape: np.ndarray, table: np.ndarray,
                  brick: np.ndarray | None) -> None:
        """The lookup grid: origin (3,) mm, cell mm, shape (3,) cells per axis, table (G,) the nearest node per cell in
        bricks of ``brick`` (3,) cells (:func:`kernels.grid_layout`). ``brick`` None: a table in plain C order (a
        prepared skin stored before the bricks), laid out in bricks here, its last cells repeated up to whole bricks,
        so that every point finds the node it found before."""
        shape = np.asarray(shape, dtype=np.int64)
        if brick is None:
            brick = self._grid_brick()
            plain = np.asarray(table).reshape(tuple(shape))
            plain = np.pad(plain, [(0, int(pad)) for pad in -shape % brick], mode="edge")
            shape, table = np.array(plain.shape, dtype=np.int64), kernels.brick_order(plain, brick)
        self.grid_origin_ = np.asarray(origin, dtype=np.float64)
        self.grid_cell_mm_ = cell_mm
        self.grid_shape_ = shape
        self.grid_brick_ = np.asarray(brick, dtype=np.int64)
        self.grid_layout_ = kernels.grid_layout(shape, self.grid_brick_)
        self.grid_table_ = np.ascontiguousarray(table, dtype=np.int32)

    def _build_kernel(self, tree: cKDTree) -> sp.csr_matrix:
        """(N, N) sparse biweight kernel w_ij = (1 - (|x_i - x_j| / r_i)^2)^2 over node pairs closer than r_i.

        r_i is the radius, widened up to ``edge_widening`` times where node i's neighbourhood is one-sided (a free
        edge: the tangential centroid of the neighbours within r sits 4 / (3 pi) r = 0.42 r off the node, a corner
        more): there half the disk holds no points and the intercept is extrapolated, so more points are taken.
        """
        n = self.points_.shape[0]
        r = self.radius_mm_
        pairs = tree.sparse_distance_matrix(tree, r, output_type="ndarray")
        pairs = pairs[pairs["i"] != pairs["j"]]
        i, j, dist = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), pairs["v"]
        rel = self.points_[j] - self.points_[i]
        # float: with no pair inside r (a radius below the node spacing) bincount returns integers
        mean = np.column_stack([np.bincount(i, weights=rel[:, k], minlength=n) for k in range(3)]).astype(float)
        mean /= np.maximum(np.bincount(i, minlength=n), 1)[:, None]
        normal = self.frames_[:, 2]
        tangential = mean - np.einsum("nd,nd->n", mean, normal)[:, None] * normal
        sidedness = np.clip(np.linalg.norm(tangential, axis=1) / (0.424 * r), 0.0, 1.5)
        radius = r * (1.0 + (self.edge_widening - 1.0) * sidedness)
        self.node_radius_mm_ = radius
        wide = np.flatnonzero(radius > 1.01 * r)
        if wide.size:
            keep = ~np.isin(i, wide)
            i, j, dist = i[keep], j[keep], dist[keep]
            lists = tree.query_ball_point(self.points_[wide], radius[wide])
            counts = np.array([len(found) for found in lists])
            wide_i = np.repeat(wide, counts)
            wide_j = np.concatenate([np.asarray(found, dtype=np.int64) for found in lists])
            mine = wide_i != wide_j
            wide_i, wide_j = wide_i[mine], wide_j[mine]
            i, j = np.concatenate([i, wide_i]), np.concatenate([j, wide_j])
            dist = np.concatenate([dist, np.linalg.norm(self.points_[wide_i] - self.points_[wide_j], axis=1)])
        i = np.concatenate([i, np.arange(n)])
        j = np.concatenate([j, np.arange(n)])
        import scipy.sparse as sp

        pattern = sp.csr_matrix((np.ones(i.size), (i, j)), shape=(n, n))
        rows = np.repeat(np.arange(n), np.diff(pattern.indptr))
        dist = np.linalg.norm(self.points_[pattern.indices] - self.points_[rows], axis=1)
        pattern.data = (1.0 - (dist / radius[rows]) ** 2) ** 2
        return pattern

    def prepared_skin(self) -> dict[str, np.ndarray]:
        """What :meth:`fit` builds slowly, as arrays (names and shapes: ``PREPARED_SKIN``) to store with the bases
        and give back to ``fit(skin, prepared=...)``: grid, quadrics, gates, kernel (CSR), node radii and, for a twiced
        fit, :meth:`_twicing_variance` (0.1 s a process on the default hood otherwise); ``bias_correlation`` (and
        ``bias_variance_floor`` when it has one) when the estimator was fitted with a measured one
        (:meth:`surface_samples`, core.loop.scan_skin)."""
        self._check_fitted()
        twicing = {"twicing_variance": self._twicing_ratio()} if self.twicing_ else {}
        if self.bias_measured_:
            twicing["bias_correlation"] = np.array([self.bias_correlation_])
        if self.bias_variance_floor_ > 0:
            twicing["bias_variance_floor"] = np.array([self.bias_variance_floor_])
        return twicing | {
            "spacing": np.array([self.spacing_mm_]), "radius": np.array([self.radius_mm_]),
            "gate2": self.gate2_, "quadric": self.quadric_, "node_radius": self.node_radius_mm_,
            "grid_origin": self.grid_origin_, "grid_cell": np.array([self.grid_cell_mm_]),
            "grid_shape": self.grid_shape_, "grid_table": self.grid_table_, "grid_brick": self.grid_brick_,
            "kernel_indptr": self.kernel_.indptr.astype(np.int64),
            "kernel_indices": self.kernel_.indices.astype(np.int32), "kernel_data": self.kernel_.data,
        }  # fmt: skip

    # ------------------------------------------------------------------------------------------------ per scan
    def _check_fitted(self) -> None:
        if not hasattr(self, "kernel_"):
            raise ScanError("ScanFieldEstimator is not fitted: call fit(skin) first")

    def _scan_points(
        self, points: np.ndarray, transform: np.ndarray | None = None, *, moments: bool = False, workers: int = 0,
        fast: bool | None = None, rows: bool = True,
    ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """Points (M, 3) on the skin: their rows (K,) int64, nodes (K,) int32, tangent coordinates u, v (K,) and
        distances (K,) (float32, mm), and with ``moments`` the per-node cell sums (N, 9) of [1, u, v, uu, uv, vv, d,
        du, dv] (else None). Without ``rows`` the rows are not kept (None: 8 bytes a point that a field does not need).

        transform: optional (4, 4) applied to the points first (scanner -> part frame); it is folded into the one
        affine map to grid units, so the part-frame points are never formed. Points outside the grid are clamped
        onto its border cells, whose nodes lie farther away than the gates allow: the gates drop them (and NaN points)
        without a separate mask.
        The points go in blocks of ``kernels.BLOCK_POINTS`` (no temporary larger than a block); each thread
        (``workers``, 0 = one per core up to 4) owns a contiguous run of blocks, its part of the output and its own
        cell sums. ``fast``: the compiled kernels (None: by the scan's size, ``kernels.for_points``).
        """
        m = points.shape[0]
        fast = kernels.for_points(m) if fast is None else fast
        affine, hi = self._grid_map(transform)
        block = kernels.BLOCK_POINTS
        n_blocks = -(-m // block)
        if workers <= 0:
            workers = min(kernels.threads(), m // _CHUNK_POINTS)
        workers = max(1, min(workers, n_blocks))
        out = (np.empty(m if rows else 0, np.int64), np.empty(m, np.int32), np.empty(m, np.float32),
               np.empty(m, np.float32), np.empty(m, np.float32))  # fmt: skip
        n = self.points_.shape[0]
        cells = [np.zeros((n, 9)) if moments else None for _ in range(workers)]
        first = np.linspace(0, n_blocks, workers + 1).astype(np.int64) * block

        def run(w: int) -> int:
            begin = position = int(first[w])
            scratch = out[0] if rows else np.empty(block, np.int64)  # rows not kept: one block's worth, rewritten
            for start in range(int(first[w]), min(int(first[w + 1]), m), block):
                position += kernels.locate_block(
                    points, start, min(start + block, m), affine, hi, self.grid_layout_, self.grid_table_,
                    self.grid_cell_mm_, self.node_table_, float(self.max_distance_mm), scratch[position:] if rows
                    else scratch, *(a[position:] for a in out[1:]), cells[w] if fast else None, fast)  # fmt: skip
            if moments and not fast:  # the numpy path bins the thread's points once (per block: nine (N,) bincounts)
                kernels.add_moments(*(a[begin:position] for a in out[1:]), 1.0, cells[w], fast)
            return position - begin

        if workers == 1:
            counts = [run(0)]
        else:
            with ThreadPoolExecutor(workers) as pool:
                counts = list(pool.map(run, range(workers)))
        total = counts[0]
        for w in range(1, workers):  # close the gaps between the threads' parts (moving down, so in place)
            for a in out if rows else out[1:]:
                a[total : total + counts[w]] = a[first[w] : first[w] + counts[w]]
            total += counts[w]
            if moments:
                cells[0] += cells[w]
        return (out[0][:total] if rows else None, *(a[:total] for a in out[1:]), cells[0])

    def _grid_map(self, transform: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The (3, 4) affine map of a point to grid units (``transform`` (4, 4) first, when given) and the last cell
        index (3,) per axis."""
        rotation, shift = (np.eye(3), np.zeros(3)) if transform is None else (transform[:3, :3], transform[:3, 3])
        scale = 1.0 / self.grid_cell_mm_
        affine = np.column_stack([rotation * scale, (shift - self.grid_origin_) * scale])
        return affine, self.grid_shape_.astype(np.float64) - 1.0

    def _locate(
        self, points: np.ndarray, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rows, nodes, u, v and distances of the points on the skin (:meth:`_scan_points`, threaded)."""
        return self._scan_points(points, transform)[:5]

    def _locate_chunk(
        self, points: np.ndarray, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_locate` in one thread."""
        return self._scan_points(points, transform, workers=1)[:5]

    def point_distances(self, points_mm: np.ndarray) -> PointDistances:
        """Signed distance of each scan point (M, 3), mm, part frame, to the nominal skin; see PointDistances."""
        self._check_fitted()
        points = np.asarray(points_mm, dtype=np.float64)
        m = points.shape[0]
        rows, j, u, v, d = self._locate(points)
        distance = np.full(m, np.nan)
        node = np.full(m, -1, dtype=np.int64)
        tangent = np.full((m, 2), np.nan)
        distance[rows], node[rows], tangent[rows, 0], tangent[rows, 1] = d, j, u, v
        return PointDistances(distance, node, tangent)

    def distance_gradient(self, located: PointDistances) -> np.ndarray:
        """(M, 3) gradient of the signed distance with respect to the point position (the nominal surface normal at
        the point, from the node's quadric); NaN rows where the point is off the skin."""
        self._check_fitted()
        gradient = np.full((located.node.shape[0], 3), np.nan)
        on = np.flatnonzero(located.node >= 0)
        j = located.node[on]
        u, v = located.tangent[on, 0], located.tangent[on, 1]
        c = self.quadric_[j]
        dq_du = c[:, 0] + 2 * c[:, 2] * u + c[:, 3] * v
        dq_dv = c[:, 1] + c[:, 3] * u + 2 * c[:, 4] * v
        t1, t2, n = self.frames_[j, 0], self.frames_[j, 1], self.frames_[j, 2]
        gradient[on] = n - dq_du[:, None] * t1 - dq_dv[:, None] * t2
        return gradient

    def _raw_moments(self, cells: np.ndarray, rows: np.ndarray, fast: bool = True) -> np.ndarray:
        """Raw 3D moments (K, 14) [1, p (3), p p^T (6, upper), d, d p (3)] about the skin centroid from the per-cell
        sums (N, 9) of the cells ``rows`` (K,).

        A point of cell j is taken at x_j + u t1_j + v t2_j: its offset along n_j (below a millimetre) moves it in
        node i's tangent plane by that times the small angle between n_i and n_j, which is negligible.
        """
        return kernels.raw_moments(cells, self.moment_basis_, rows, fast)

    def _node_fits(self, mixed: np.ndarray, fast: bool = True, equivalent: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """Weighted plane fits d = a + b_u u + b_v v per node from kernel-mixed raw moments (N, 14): each node's 3x3
        normal equations in its own tangent frame.
        Returns coefficients (N, 3) [a mm, b_u, b_v], weighted point count (N,), intercept variance inflation (N,) and
        with ``equivalent`` the equivalent kernel's rows (N, 4) [c_i, w_i] (:func:`kernels.node_fits`), else None.
        """
        return kernels.node_fits(mixed, self.frames_, self.t1_dot_x_, self.t2_dot_x_, fast, equivalent)

    def field(self, points_mm: np.ndarray, transform: np.ndarray | None = None) -> DisplacementField:
        """The signed normal displacement (N,) mm of every skin node from scan points (M, 3), mm, in the part frame
        (or in the scanner frame with ``transform`` (4, 4) the scanner-to-part registration).

        NaN where the scan gives no support; ``noise_rms`` is the RMS of the inlier residuals along the normal.
        """
        self._check_fitted()
        points = np.asarray(points_mm, dtype=np.float64)
        fast = kernels.for_points(points.shape[0])  # one choice for the whole scan
        # a cloud in no spatial order (shuffled, hashed) is sorted by tiles first: the field needs no point order
        points = kernels.tile_order(points, *self._grid_map(transform), self.grid_cell_mm_, fast)
        _, j, u, v, d, cells = self._scan_points(points, transform, moments=True, fast=fast, rows=False)
        n = self.points_.shape[0]
        if j.size == 0:
            return DisplacementField(self.skin_.model_id, np.full(n, np.nan), 0.0, float("nan"))
        raw = self._raw_moments(cells, np.arange(n), fast)
        mixed = self._smooth(raw)
        coef = self._node_fits(mixed, fast)[0]
        logger.info("first pass: %d points on the skin", j.size)
        # Second pass: drop points far from their own node's fit and take their sums out of the cells and, through
        # the few kernel columns of those cells, out of the mixed moments. The residuals go by blocks (none of the
        # scan's size is kept): the noise is the RMS of the inliers' residuals from the first-pass fit.
        every = slice(None, None, max(1, j.size // 100_000))  # 1e5 residuals fix the scale
        sample = kernels.plane_residuals(*(np.ascontiguousarray(a[every]) for a in (j, u, v, d)), coef, fast)
        spread = np.abs(sample[np.isfinite(sample)])
        sigma = 1.4826 * float(np.median(spread)) if spread.size else np.inf
        limit = self.outlier_sigma * max(sigma, 1e-6)
        drop, inliers, squares = kernels.outliers(j, u, v, d, coef, limit, fast)
        rows = np.unique(j[drop])
        removed = np.zeros_like(cells)
        if drop.size:
            kernels.add_moments(j[drop], u[drop], v[drop], d[drop], 1.0, removed, fast)
            cells -= removed
        # One pass over the kernel: the dropped points' moments out of the mixed moments (through the kernel columns
        # of their cells), and the per-node sums the support test and the error model need.
        kernel = self.kernel_
        removed_raw = self._raw_moments(removed, rows, fast)
        squared, nearby = kernels.kernel_sums(kernel.indptr, kernel.indices, kernel.data, cells[:, 0], rows,
                                              removed_raw, _NEAR_WEIGHT, mixed, fast)
        raw[rows] -= removed_raw  # the kept points' raw moments (linear in the cell sums): their counts and positions
        coef, weight, inflation, rows = self._node_fits(mixed, fast, equivalent=True)
        if self.twicing_:  # a second twicing pass removes little more (coarse: bias RMS 0.0043 -> 0.0035 mm)
            coef = coef + self._twice(cells, coef, mixed, fast)
        supported = (
            (weight >= self.min_points)
            & (inflation <= self.max_inflation)
            & (nearby >= max(1.0, self.min_points / 4))
            & np.isfinite(coef[:, 0])
        )
        value = np.where(supported, coef[:, 0], np.nan)
        noise = float(np.sqrt(squares / inliers)) if inliers else float("nan")
        logger.info("second pass: %d inliers, %d of %d nodes seen", j.size - drop.size, supported.sum(), n)
        errors = self._error_model(raw, squared, weight, inflation, rows, supported, noise, fast)
        return DisplacementField(self.skin_.model_id, value, float(supported.mean()), noise, errors)

    def _smooth(self, values: np.ndarray) -> np.ndarray:
        """K @ values (N, C) by the kernel's row blocks on as many threads (scipy's sparse products release the GIL):
        14 columns at paper resolution 15.5 -> 9.1 ms on 2 cores, the same numbers (each row is one block's)."""
        blocks = self.kernel_blocks_
        if len(blocks) == 1:
            return self.kernel_ @ values
        out = np.empty((self.kernel_.shape[0], values.shape[1]))

        def run(k: int) -> None:
            rows, matrix = blocks[k]
            out[rows] = matrix @ values

        kernels.on_threads(run, len(blocks))
        return out

    def _twice(self, cells: np.ndarray, coef: np.ndarray, mixed: np.ndarray, fast: bool) -> np.ndarray:
        """The twicing pass (Tukey): the same plane fit of the points' residuals from their own node's plane,
        (N, 3) to add to ``coef``. The smoothing's bias is about the kernel's second moment times the curvature of the
        *displacement* (a scan of the undeformed part has almost none: 0.0004 mm RMS on the coarse hood); the fit of
        the residuals measures it and adding it back leaves a bias of higher order.

        Built from the cell sums alone: the residuals r = d - a_j - b_u u - b_v v of cell j's points sum to
        [r, r u, r v] = [D - a N - b_u U - b_v V, DU - a U - b_u UU - b_v UV, DV - a V - b_u UV - b_v VV], so no
        pass over the points; only the d columns of the mixed moments change, the normal equations are the same.
        """
        a, bu, bv = (np.where(np.isfinite(coef[:, k]), coef[:, k], 0.0) for k in range(3))
        count, u, v, uu, uv, vv, d, du, dv = cells.T
        residual = cells.copy()
        residual[:, 6] = d - a * count - bu * u - bv * v
        residual[:, 7] = du - a * u - bu * uu - bv * uv
        residual[:, 8] = dv - a * v - bu * uv - bv * vv
        twice = mixed.copy()
        twice[:, 10:] = self._smooth(self._raw_moments(residual, np.arange(cells.shape[0]), fast)[:, 10:])
        return self._node_fits(twice, fast)[0]

    def _twicing_ratio(self) -> np.ndarray:
        """``twicing_variance_`` (N,): taken from the prepared skin, else :meth:`_twicing_variance` once per
        estimator."""
        if not hasattr(self, "twicing_variance_"):
            self.twicing_variance_ = self._twicing_variance()
        return self.twicing_variance_

    def _twicing_variance(self) -> np.ndarray:
        """(N,) the twiced fit's node variance over the plain fit's, from the skin's own kernel at one point per node
        (uniform density): diag((2 L - L L) D (2 L - L L)^T) / diag(L D L^T) (:func:`kernels.twiced_variance`).
        Per scan that diagonal would take the kernel's two-ring product (about 14M terms on the default hood, a
        quarter of the scan's time); the ratio depends on the kernel's shape and the skin's edges and cut-outs, not on
        the scan: 1.7-1.8 inside, less at free edges. Where a scan's own hole makes a node one-sided the interior
        ratio over-states its variance by about 7 % (conservative)."""
        n = self.points_.shape[0]
        cells = np.zeros((n, 9))
        cells[:, 0] = 1.0
        fast = kernels.for_points(0)  # compiled only where the kernels are loaded already
        raw = self._raw_moments(cells, np.arange(n), fast)
        kernel = self.kernel_
        plain, twiced = kernels.twiced_variance(kernel.indptr, kernel.indices, kernel.data,
                                                self._node_fits(self._smooth(raw), fast, equivalent=True)[3], raw,
                                                fast)
        return np.where(plain > 0, twiced / np.where(plain > 0, plain, 1.0), 1.0)

    def surface_samples(self, displacement: np.ndarray, jacobian: np.ndarray) -> np.ndarray:
        """(7 N, 3) mm, a noise-free scan of the skin displaced by ``displacement`` (N, 3) mm: per node the node and
        a ring of six points a third of the mesh spacing out in its tangent plane, lifted onto its nominal quadric
        (the surface this step measures against, so the undeformed part reads 4e-6 mm RMS on the coarse hood), each
        moved by the node's displacement plus the tangential Jacobian ``jacobian`` (N, 3, 3) (d u_c / d x_d, 1) times
        its offset. A displaced point may land in a neighbour's cell, as on a scan of a part that slid in its plane.

        What the scan step's own bias is measured on (core.loop.scan_skin): the field of such a cloud, through
        :meth:`field` itself (cells, kernel, free edges, twicing), minus what a scan reads of the state. The ring's
        radius sets the rough part of that bias: against noise-free synthetic scans of other FE states (issue 15
        run 13) it gives 0.92-1.06 of their bias correlation, where points spread uniformly over each node's area
        (a ring at about 0.4 spacing) give 0.58-0.69 and one point per node 0.26-0.56."""
        self._check_fitted()
        n = self.points_.shape[0]
        displacement = np.asarray(displacement, dtype=np.float64)
        jacobian = np.asarray(jacobian, dtype=np.float64)
        if displacement.shape != (n, 3) or jacobian.shape != (n, 3, 3):
            raise ScanError(f"displacement must be (N={n}, 3) and jacobian (N, 3, 3); got {displacement.shape} and "
                            f"{jacobian.shape}")
        angle = np.concatenate([[np.nan], 2.0 * np.pi * np.arange(6) / 6])
        u = np.nan_to_num(np.cos(angle)) * self.spacing_mm_ / 3.0
        v = np.nan_to_num(np.sin(angle)) * self.spacing_mm_ / 3.0
        c = self.quadric_
        z = c[:, :1] * u + c[:, 1:2] * v + c[:, 2:3] * u * u + c[:, 3:4] * u * v + c[:, 4:5] * v * v  # (N, 7)
        offset = np.einsum("nk,nd->nkd", np.broadcast_to(u, z.shape), self.frames_[:, 0])
        offset += np.einsum("nk,nd->nkd", np.broadcast_to(v, z.shape), self.frames_[:, 1])
        offset += z[..., None] * self.frames_[:, None, 2]
        moved = displacement[:, None, :] + np.einsum("ncd,nkd->nkc", jacobian, offset)
        return (self.points_[:, None, :] + offset + moved).reshape(-1, 3)

    def _error_model(self, raw: np.ndarray, squared: np.ndarray, weight: np.ndarray, inflation: np.ndarray,
                     rows: np.ndarray, supported: np.ndarray, noise_mm: float, fast: bool) -> FieldErrorModel:
        """The node errors this smoothing makes of independent point noise (``noise_mm`` per point, along the normal).

        The node values are a = A m of the cells' mean distances m (Var m_j = noise^2 / n_j), A = L the plane fit's
        equivalent weights (L_ij = K_ij (c_i n_j + w_i . P_j), :func:`kernels.covariance_sums`) or A = 2 L - L L for
        the twiced fit (the residual fit adds L (m - a)), so Cov(a) = noise^2 A D A^T, D = diag(1 / n).
        Node std: noise sqrt(sum_j K_ij^2 n_j) / W_i times the square root of the fit's intercept inflation (the
        diagonal of L D L^T where the kernel's square is locally proportional to it; measured 0.96-1.0 of a Monte
        Carlo of the smoother, 1.08 at free edges), for the twiced fit times :meth:`_twicing_variance`. squared (N,):
        sum_j K_ij^2 n_j (:func:`kernels.kernel_sums`); weight W (N,), inflation (N,), rows (N, 4) [c_i, w_i] of L:
        the second pass's :func:`kernels.node_fits`; raw (N, 14): the kept points' raw moments per cell (counts,
        position sums).
        Correlation sum g_i = sum_k Cov_ik / (s_i s_k) = (A D A^T t)_i / s_i, t = 1 / s: two (plain) or four (twiced)
        products with L (:func:`kernels.covariance_sums`), no N x N matrix. A smooth projection of the field sees
        these row sums: the kernel-average model they replace over-stated it 1.4 times (issue 15 run 7).
        """
        if not np.isfinite(noise_mm):
            return FieldErrorModel.none()
        with np.errstate(invalid="ignore", divide="ignore"):
            spread = np.sqrt(squared * np.maximum(inflation, 1.0)) / weight  # std per unit point noise
        if self.twicing_:
            spread = spread * np.sqrt(self._twicing_ratio())
        supported = supported & np.isfinite(spread) & (spread > 0)
        t = np.where(supported, 1.0 / np.where(supported, spread, 1.0), 0.0)
        kernel = self.kernel_
        correlation = kernels.covariance_sums(kernel.indptr, kernel.indices, kernel.data, rows, raw, t, self.twicing_,
                                              fast)
        return FieldErrorModel("scan", np.where(supported, noise_mm * spread, np.nan),
                               np.where(supported, np.maximum(correlation, 1.0), 1.0), float(self.radius_mm_),
                               bias_correlation=self.bias_correlation_,
                               bias_variance_floor=self.bias_variance_floor_)


_PREPARED: dict[tuple, ScanFieldEstimator] = {}
_STORED: dict[tuple, Callable[[], Mapping[str, np.ndarray]]] = {}


def register_prepared_skin(skin: SkinSurface, load: Callable[[], Mapping[str, np.ndarray]]) -> None:
    """Offer a stored prepared skin for ``skin`` (default estimator options): ``load()`` returns the arrays of
    :meth:`ScanFieldEstimator.prepared_skin` (e.g. read from a bases file, io/bases.py) and is called only when a
    scan of this skin is first turned into a field, instead of rebuilding the grid, quadrics and kernel."""
    _STORED[(skin.model_id, skin.n_nodes)] = load


def prepared_estimator(skin: SkinSurface, **options: float | None) -> ScanFieldEstimator:
    """A fitted :class:`ScanFieldEstimator` for ``skin``, reused across calls with the same skin and options.

    The preparation (grid, kernel, quadrics) costs far more than one scan; callers that hold a skin for many scans
    (the scan node, the CLI) get it once, from a registered stored preparation (:func:`register_prepared_skin`)
    where there is one for the default options. Keyed by ``model_id``, node count and the options; keeps the last 4.
    """
    key = (skin.model_id, skin.n_nodes, tuple(sorted(options.items())))
    if key not in _PREPARED:
        if len(_PREPARED) >= 4:
            _PREPARED.pop(next(iter(_PREPARED)))
        stored = _STORED.get((skin.model_id, skin.n_nodes)) if not options else None
        _PREPARED[key] = ScanFieldEstimator(**options).fit(skin, prepared=None if stored is None else stored())
    return _PREPARED[key]


def warm_up(estimator: ScanFieldEstimator, points: int = 1_000_000) -> DisplacementField:
    """Run the fitted estimator's whole scan path once on a scan-sized cloud of its own skin, so that the first real
    scan runs at steady-state speed: the compiled kernels are loaded (or compiled, the first time after an install),
    the threads, the allocator's buffers of a scan's size and the sparse products are exercised.

    The cloud: about ``points`` points, each skin node repeated with small tangential offsets (a third of a mesh
    spacing), every 50th pushed 1 mm off along its normal (so the outlier pass runs too); as long as one scan.
    Returns its field (for a caller that warms up what it does with a field).
    """
    estimator._check_fitted()
    kernels.load()  # a node serves many scans: the compiled path whatever their size
    nodes, frames = estimator.points_, estimator.frames_
    copies = max(1, -(-points // nodes.shape[0]))
    angle = 2.0 * np.pi * np.arange(copies) / copies
    step = estimator.spacing_mm_ / 3.0
    cos, sin = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
    cloud = (nodes[None] + step * (cos * frames[None, :, 0] + sin * frames[None, :, 1])).reshape(-1, 3)
    cloud[::50] += np.tile(frames[:, 2], (copies, 1))[::50]
    field = estimator.field(cloud)
    estimator.point_distances(cloud[:20_000])
    return field


def _check_points(points_mm: np.ndarray, skin_size: float) -> np.ndarray:
    """Validate a raw scan (M, 3) mm of a part whose skin's bounding-box diagonal is ``skin_size`` mm; returns its
    finite rows. Raises ScanError naming the problem."""
    points = np.asarray(points_mm, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ScanError(f"scan points must be an (M, 3) array in mm; got shape {points.shape}")
    if points.shape[0] == 0:
        raise ScanError("scan is empty: 0 points")
    if not np.isfinite(points).all():  # one flat pass; the row mask only for a scan with non-finite points
        finite = np.isfinite(points[:, 0] + points[:, 1] + points[:, 2])  # any NaN or inf makes the sum non-finite
        if not finite.any():
            raise ScanError(f"scan has no finite points: all {points.shape[0]} points are NaN or infinite")
        points = np.compress(finite, points, axis=0)
    # Unit check on robust extents: a part seen partly still spans a good fraction of its own size.
    lo, hi = np.percentile(points[:: max(1, points.shape[0] // 50000)], [1, 99], axis=0)
    scan_size = float(np.linalg.norm(hi - lo))
    ratio = scan_size / skin_size
    if 2e-4 <= ratio <= 1e-2:
        raise ScanError(
            f"scan appears to be in metres: its extent is {scan_size:.4g} against a skin of {skin_size:.4g} mm "
            f"(ratio {ratio:.2g}); expected millimetres, multiply the points by 1000"
        )
    if ratio < 0.02 or ratio > 5:
        raise ScanError(
            f"scan scale does not match the part: extent {scan_size:.4g} mm against a skin of {skin_size:.4g} mm "
            f"(ratio {ratio:.2g}); expected a scan in millimetres of this part"
        )
    return points


def field_from_scan(
    skin: SkinSurface,
    points_mm: np.ndarray,
    *,
    scanner_pose: np.ndarray | None = None,
    markers_mm: np.ndarray | None = None,
    markers_nominal_mm: np.ndarray | None = None,
    datum_mask: np.ndarray | None = None,
    datum_tolerance_mm: float = 0.005,
    min_coverage: float = 0.2,
    min_overlap: float = 0.02,
    estimator: ScanFieldEstimator | None = None,
    marker_std_mm: float | None = None,
) -> tuple[DisplacementField, RegistrationResult]:
    """A raw scan (M, 3) mm in the scanner frame -> registered -> signed normal displacement per skin node.

    scanner_pose: (4, 4) nominal scanner-to-part transform (the cell's calibration); identity if None, i.e. the points
        are already in the part frame.
    markers_mm, markers_nominal_mm: (K, 3) fixture markers measured by the scanner (scanner frame) and their nominal
        positions (part frame), matched row by row; K >= 3 gives the coarse registration.
    datum_mask: (N,) bool, skin nodes where the part cannot move (near fixed boundaries): the fine alignment uses only
        scan points there, so the deformation being measured elsewhere is not swallowed.
    datum_tolerance_mm: the fine alignment corrects only rigid-motion directions the datum determines to this RMS
        motion over the skin (see register_scan).
    min_coverage: minimum fraction of skin nodes with a value; min_overlap: minimum fraction of scan points on the skin.
    estimator: a fitted ScanFieldEstimator (else one is prepared and cached for this skin).
    marker_std_mm: the scanner's marker-centre noise (mm per coordinate), for the registration's pose covariance;
        None: estimated from the marker residual. A stated value the marker residual rejects
        (``registration.marker_noise``, :func:`~hood_decomp.core.scan.registration.check_marker_noise`) is replaced
        by the estimate, with a warning logged.
    Returns the DisplacementField with its error model (node std and correlation of the smoothing, the marker
    registration's pose covariance) (paper: the condensed signed distance field) and the RegistrationResult.
    Raises ScanError for an empty or all-NaN scan, a scan in metres, no overlap with the part or too little coverage.
    """
    est = estimator if estimator is not None else prepared_estimator(skin)
    points = _check_points(points_mm, est.skin_size_mm_)
    registration = register_scan(
        points,
        est,
        scanner_pose=scanner_pose,
        markers_mm=markers_mm,
        markers_nominal_mm=markers_nominal_mm,
        datum_mask=datum_mask,
        tolerance_mm=datum_tolerance_mm,
        marker_std_mm=marker_std_mm,
    )
    logger.info("registered by %s: overlap %.1f%%", registration.method, 100.0 * registration.overlap)
    if registration.marker_noise is not None and not registration.marker_noise.accepted:
        logger.warning("marker registration: %s", registration.marker_noise.reason)
    if registration.overlap < min_overlap:
        raise ScanError(
            f"scan does not overlap the part: {registration.overlap:.2%} of {points.shape[0]} points lie within "
            f"{est.max_distance_mm} mm of the nominal skin after registration (expected at least {min_overlap:.0%})"
        )
    field = est.field(points, registration.transform)
    if registration.n_markers and field.error_model is not None and field.error_model.kind == "scan":
        # the registration error moves the whole part: its covariance travels with the field (FieldErrorModel)
        field = dataclasses.replace(field, error_model=dataclasses.replace(
            field.error_model, pose_covariance=registration.pose_covariance, pose_center=registration.pose_center))
    if field.coverage < min_coverage:
        raise ScanError(
            f"scan coverage too low: {field.coverage:.1%} of {skin.n_nodes} skin nodes have support "
            f"(minimum {min_coverage:.0%})"
        )
    return field, registration
