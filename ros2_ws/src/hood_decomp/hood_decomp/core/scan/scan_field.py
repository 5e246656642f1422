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
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.spatial import cKDTree

from hood_decomp.core.scan.registration import RegistrationResult, register_scan
from hood_decomp.core.types import DisplacementField, FieldErrorModel, SkinSurface
from hood_decomp.errors import ScanError

logger = logging.getLogger(__name__)

# A lookup grid finer than this many cells would cost more memory than it saves time.
_MAX_GRID_CELLS = 12_000_000
# Scans larger than this many points per core are located in parallel threads.
_CHUNK_POINTS = 200_000
# Nominal nodes used for each node's quadric (the node itself included).
_QUADRIC_NEIGHBOURS = 13
# How far the smoothing bias is correlated (sum of correlation coefficients, in nodes): measured on the default hood
# against the FE truth (the bias of noise-free scans projected on smooth fields: 70-260 nodes in one state), and set
# where the within-model test's false-alarm rate on 120 scans came down (300: 12.5 %; benchmarks/RESULTS.md).
SMOOTHING_BIAS_CORRELATION = 1000.0
# Upper triangle of a symmetric 3x3 matrix: xx xy xz yy yz zz.
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


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


def _unique_edges(triangles: np.ndarray) -> np.ndarray:
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0)


def _tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) completing each normal to a right-handed frame (t1, t2, n)."""
    helper = np.zeros_like(normals)
    use_x = np.abs(normals[:, 0]) < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(normals, t1)


def _solve_3x3(m: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched symmetric 3x3 solve by the adjugate: solutions (K, 3) and the (0, 0) entry of the inverse (K,).

    m: (K, 6) upper triangle [m00, m01, m02, m11, m12, m22]; rhs: (K, 3). Singular systems give NaN.
    """
    m00, m01, m02, m11, m12, m22 = m.T
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = np.where(np.abs(det) > 1e-12 * np.abs(m00 * m11 * m22) + 1e-300, 1.0 / det, np.nan)
    r0, r1, r2 = rhs.T
    solution = np.column_stack(
        [
            (c00 * r0 + c01 * r1 + c02 * r2) * inv_det,
            (c01 * r0 + c11 * r1 + c12 * r2) * inv_det,
            (c02 * r0 + c12 * r1 + c22 * r2) * inv_det,
        ]
    )
    return solution, c00 * inv_det


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
    """

    def __init__(
        self,
        radius_mm: float | None = None,
        max_distance_mm: float = 5.0,
        min_points: float = 8.0,
        max_inflation: float = 8.0,
        outlier_sigma: float = 4.0,
        edge_widening: float = 2.0,
    ) -> None:
        self.radius_mm = radius_mm
        self.max_distance_mm = max_distance_mm
        self.min_points = min_points
        self.max_inflation = max_inflation
        self.outlier_sigma = outlier_sigma
        self.edge_widening = edge_widening

    # ------------------------------------------------------------------------------------------------ preparation
    def fit(self, skin: SkinSurface) -> ScanFieldEstimator:
        """Prepare the nominal skin: (N, 3) points and unit normals, (T, 3) triangles, mm."""
        points = np.asarray(skin.points, dtype=np.float64)
        normals = np.asarray(skin.normals, dtype=np.float64)
        n = points.shape[0]
        if points.ndim != 2 or points.shape[1] != 3 or n < 4 or normals.shape != points.shape:
            raise ScanError(f"skin must have (N>=4, 3) points and normals; got {points.shape} and {normals.shape}")
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        edges = _unique_edges(np.asarray(skin.triangles, dtype=np.int64))
        edge_length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
        spacing = float(np.median(edge_length))
        longest = np.zeros(n)
        np.maximum.at(longest, edges[:, 0], edge_length)
        np.maximum.at(longest, edges[:, 1], edge_length)

        self.skin_ = skin
        self.spacing_mm_ = spacing
        self.radius_mm_ = float(self.radius_mm) if self.radius_mm is not None else 2.5 * spacing
        self.center_ = points.mean(axis=0)
        self.points_ = points
        tangent1, tangent2 = _tangent_frames(normals)
        self.frames_ = np.stack([tangent1, tangent2, normals], axis=1)  # (N, 3, 3) rows t1, t2, n
        self._prepare_moment_maps(points - self.center_, tangent1, tangent2)
        # A point belongs to node j when it lies within this tangential distance (grid lookups may be off by about
        # one spacing, hence the generous factor); beyond it, it is past a free edge. So a point on the surface's
        # own continuation up to about 2.5 spacings past a free edge still counts as skin.
        self.gate2_ = (1.6 * longest + 0.5 * spacing) ** 2
        tree = cKDTree(points)
        self.quadric_ = self._fit_quadrics(tree)
        table = np.column_stack([self.frames_.reshape(n, 9), self.quadric_, self.gate2_])
        self.node_table32_ = table.astype(np.float32)
        self._build_grid()
        self.kernel_ = self._build_kernel(tree)
        # Nodes within half the radius: a node needs scan points this close, or it sits in a gap of the scan and a
        # value there would be interpolated across the gap rather than measured.
        near = self.kernel_.copy()
        near.data = (near.data >= 0.75**2).astype(np.float64)
        near.eliminate_zeros()
        self.near_kernel_ = near
        self.kernel_columns_ = self.kernel_.tocsc()  # for taking a few cells' outliers back out
        self.kernel_squared_ = self.kernel_.multiply(self.kernel_).tocsr()  # for the node variances
        return self

    def _prepare_moment_maps(self, x: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> None:
        """Per-node linear maps from cell sums to raw 3D moments about the centroid, and back to tangent frames.

        A point of cell j sits at x_j + u t1_j + v t2_j (x_j about the centroid), so its first moments are
        [1, u, v] @ [x_j; t1_j; t2_j] and its second moments [1, u, v, uu, uv, vv] @ (6 x 6 map) in upper-triangle
        order. For node i, the tangent quadratic forms t_a^T S t_b of a moment matrix S are (3 x 6 map) @ S.
        """
        self.moment_basis_ = np.stack([x, t1, t2], axis=1)  # (N, 3, 3)

        def sym(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            """Upper triangle (N, 6) of a b^T + b a^T."""
            return np.stack([a[:, p] * b[:, q] + a[:, q] * b[:, p] for p, q in _UPPER], axis=1)

        self.second_basis_ = np.stack([sym(x, x) / 2, sym(x, t1), sym(x, t2), sym(t1, t1) / 2, sym(t1, t2),
                                       sym(t2, t2) / 2], axis=1)  # fmt: skip
        # t_a^T S t_b = sum over the upper triangle of S times sym(t_a, t_b), diagonal entries counted once.
        diagonal = np.array([p == q for p, q in _UPPER])
        self.tangent_quad_ = np.stack([sym(t1, t1), sym(t1, t2), sym(t2, t2)], axis=1)
        self.tangent_quad_[:, :, diagonal] /= 2
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
        cell = self.spacing_mm_
        while np.prod(np.ceil(extent / cell)) > _MAX_GRID_CELLS:
            cell *= 1.25
        shape = np.ceil(extent / cell).astype(np.int64)
        keys = np.floor((self.points_ - lo) / cell).astype(np.int64)
        table = np.full(tuple(shape), -1, dtype=np.int64)
        table[keys[:, 0], keys[:, 1], keys[:, 2]] = np.arange(self.points_.shape[0])
        nearest = ndimage.distance_transform_edt(table < 0, return_distances=False, return_indices=True)
        self.grid_origin_ = lo
        self.grid_cell_mm_ = float(cell)
        self.grid_shape_ = shape
        self.grid_strides_ = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.float64)
        # Node positions in grid units, one contiguous array per axis (gathered per axis in _locate_chunk).
        self.grid_points_ = tuple(np.ascontiguousarray((self.points_[:, k] - lo[k]) / cell) for k in range(3))
        self.grid_table_ = table[tuple(nearest)].ravel().astype(np.int32)

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
        dist = np.concatenate([dist, np.zeros(n)])
        weight = (1.0 - (dist / radius[i]) ** 2) ** 2
        return sp.csr_matrix((weight, (i, j)), shape=(n, n))

    # ------------------------------------------------------------------------------------------------ per scan
    def _check_fitted(self) -> None:
        if not hasattr(self, "kernel_"):
            raise ScanError("ScanFieldEstimator is not fitted: call fit(skin) first")

    def _locate(
        self, points: np.ndarray, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Points (M, 3) on the skin: their rows (K,), nodes (K,), tangent coordinates u, v (K,) and distances (K,).

        Large scans are split into one chunk per core and located in threads (numpy releases the GIL in these loops).
        """
        workers = min(os.cpu_count() or 1, 4, points.shape[0] // _CHUNK_POINTS)
        if workers < 2:
            return self._locate_chunk(points, transform)
        bounds = np.linspace(0, points.shape[0], workers + 1).astype(np.int64)
        with ThreadPoolExecutor(workers) as pool:
            parts = list(pool.map(lambda k: self._locate_chunk(points[bounds[k] : bounds[k + 1]], transform),
                                  range(workers)))  # fmt: skip
        rows = np.concatenate([part[0] + bounds[k] for k, part in enumerate(parts)])
        return rows, *(np.concatenate([part[i] for part in parts]) for i in range(1, 5))

    def _locate_chunk(
        self, points: np.ndarray, transform: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One chunk of :meth:`_locate`.

        transform: optional (4, 4) applied to the points first (scanner -> part frame); it is folded into the one
        affine map to grid units, so the part-frame points are never formed. Points outside the grid are clamped
        onto its border cells, whose nodes lie farther away than the gates allow: the gates drop them (and NaN points)
        without a separate mask. Offsets from the node are formed in float64 and then handled in float32 (a few mm,
        so 1e-6 mm resolution).
        """
        rotation, shift = (np.eye(3), np.zeros(3)) if transform is None else (transform[:3, :3], transform[:3, 3])
        scale = 1.0 / self.grid_cell_mm_
        to_grid, offset_grid = rotation * scale, (shift - self.grid_origin_) * scale
        # Column by column (no BLAS: a threaded BLAS call on an (M, 3) x (3, 3) product is slower, and erratic on a busy
        # machine): grid coordinates, their cell, the cell's node.
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        cell = [x * to_grid[k, 0] + y * to_grid[k, 1] + z * to_grid[k, 2] + offset_grid[k] for k in range(3)]
        flat = np.zeros(points.shape[0])
        for k in range(3):
            index = np.floor(cell[k])
            np.fmax(index, 0.0, out=index)  # fmax/fmin, unlike clip, also send NaN to a border cell
            np.fmin(index, self.grid_shape_[k] - 1.0, out=index)
            flat += index * self.grid_strides_[k]
        j = self.grid_table_[flat.astype(np.int64)].astype(np.int64)
        o = [((cell[k] - self.grid_points_[k][j]) * self.grid_cell_mm_).astype(np.float32) for k in range(3)]
        node = self.node_table32_[j]  # one gather: frame rows t1, t2, n (9), quadric (5), squared gate (1)
        u = node[:, 0] * o[0] + node[:, 1] * o[1] + node[:, 2] * o[2]
        v = node[:, 3] * o[0] + node[:, 4] * o[1] + node[:, 5] * o[2]
        w = node[:, 6] * o[0] + node[:, 7] * o[1] + node[:, 8] * o[2]
        d = w - (node[:, 9] * u + node[:, 10] * v + node[:, 11] * u * u + node[:, 12] * u * v + node[:, 13] * v * v)
        with np.errstate(invalid="ignore"):
            ok = np.flatnonzero((np.abs(d) <= self.max_distance_mm) & (u * u + v * v <= node[:, 14]))
        return ok, j[ok], u[ok], v[ok], d[ok]

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

    def _cell_moments(self, j: np.ndarray, u: np.ndarray, v: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(N, 9) sums per node cell of [1, u, v, uu, uv, vv, d, du, dv] (u, v in the cell node's frame, mm)."""
        n = self.points_.shape[0]
        columns = (None, u, v, u * u, u * v, v * v, d, d * u, d * v)
        return np.column_stack([np.bincount(j, weights=col, minlength=n + 1)[:n] for col in columns])

    def _raw_moments(self, cells: np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Raw 3D moments (K, 14) [1, p (3), p p^T (6, upper), d, d p (3)] about the skin centroid from per-cell sums
        (K, 9) of the cells ``rows``.

        A point of cell j is taken at x_j + u t1_j + v t2_j: its offset along n_j (below a millimetre) moves it in
        node i's tangent plane by that times the small angle between n_i and n_j, which is negligible.
        """
        s1 = np.einsum("nk,nkd->nd", cells[:, :3], self.moment_basis_[rows])
        s2 = np.einsum("nk,nkc->nc", cells[:, :6], self.second_basis_[rows])
        d1 = np.einsum("nk,nkd->nd", cells[:, 6:9], self.moment_basis_[rows])
        return np.column_stack([cells[:, 0], s1, s2, cells[:, 6], d1])

    def _node_fits(self, mixed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Weighted plane fits d = a + b_u u + b_v v per node from kernel-mixed raw moments (N, 14): each node's 3x3
        normal equations in its own tangent frame.
        Returns coefficients (N, 3) [a mm, b_u, b_v], weighted point count (N,) and intercept variance inflation (N,).
        """
        s0, s1, s2, d0, d1 = mixed[:, 0], mixed[:, 1:4], mixed[:, 4:10], mixed[:, 10], mixed[:, 11:14]
        ts = np.einsum("nkd,nd->nk", self.frames_[:, :2], s1)
        td = np.einsum("nkd,nd->nk", self.frames_[:, :2], d1)
        quad = np.einsum("nkc,nc->nk", self.tangent_quad_, s2)
        t1x, t2x = self.t1_dot_x_, self.t2_dot_x_
        system = np.column_stack(
            [
                s0,
                ts[:, 0] - s0 * t1x,
                ts[:, 1] - s0 * t2x,
                quad[:, 0] - 2 * ts[:, 0] * t1x + s0 * t1x * t1x,
                quad[:, 1] - ts[:, 0] * t2x - t1x * ts[:, 1] + s0 * t1x * t2x,
                quad[:, 2] - 2 * ts[:, 1] * t2x + s0 * t2x * t2x,
            ]
        )
        rhs = np.column_stack([d0, td[:, 0] - d0 * t1x, td[:, 1] - d0 * t2x])
        coef, inv00 = _solve_3x3(system, rhs)
        return coef, s0, s0 * inv00

    def field(self, points_mm: np.ndarray, transform: np.ndarray | None = None) -> DisplacementField:
        """The signed normal displacement (N,) mm of every skin node from scan points (M, 3), mm, in the part frame
        (or in the scanner frame with ``transform`` (4, 4) the scanner-to-part registration).

        NaN where the scan gives no support; ``noise_rms`` is the RMS of the inlier residuals along the normal.
        """
        self._check_fitted()
        _, j, u, v, d = self._locate(np.asarray(points_mm, dtype=np.float64), transform)
        n = self.points_.shape[0]
        if j.size == 0:
            return DisplacementField(self.skin_.model_id, np.full(n, np.nan), 0.0, float("nan"))
        cells = self._cell_moments(j, u, v, d)
        mixed = self.kernel_ @ self._raw_moments(cells)
        coef, _, _ = self._node_fits(mixed)
        logger.info("first pass: %d points on the skin", j.size)
        # Second pass: drop points far from their own node's fit and take their sums out of the cells and, through
        # the few kernel columns of those cells, out of the mixed moments.
        c = coef[j]
        residual = d - (c[:, 0] + c[:, 1] * u + c[:, 2] * v)
        finite = np.isfinite(residual)
        spread = np.abs(residual[finite][:: max(1, int(finite.sum()) // 100_000)])  # 1e5 residuals fix the scale
        sigma = 1.4826 * float(np.median(spread)) if spread.size else np.inf
        drop = np.flatnonzero(np.abs(residual) > self.outlier_sigma * max(sigma, 1e-6))
        if drop.size:
            removed = self._cell_moments(j[drop], u[drop], v[drop], d[drop])
            rows = np.unique(j[drop])
            cells = cells - removed
            mixed = mixed - self.kernel_columns_[:, rows] @ self._raw_moments(removed[rows], rows)
        coef, weight, inflation = self._node_fits(mixed)
        nearby = self.near_kernel_ @ cells[:, 0]
        supported = (
            (weight >= self.min_points)
            & (inflation <= self.max_inflation)
            & (nearby >= max(1.0, self.min_points / 4))
            & np.isfinite(coef[:, 0])
        )
        value = np.where(supported, coef[:, 0], np.nan)
        inlier = finite.copy()
        inlier[drop] = False
        noise = float(np.sqrt(np.mean(residual[inlier] ** 2))) if inlier.any() else float("nan")
        logger.info("second pass: %d inliers, %d of %d nodes seen", j.size - drop.size, supported.sum(), n)
        errors = self._error_model(cells[:, 0], weight, inflation, supported, noise)
        return DisplacementField(self.skin_.model_id, value, float(supported.mean()), noise, errors)

    def _error_model(self, counts: np.ndarray, weight: np.ndarray, inflation: np.ndarray, supported: np.ndarray,
                     noise_mm: float) -> FieldErrorModel:
        """The node errors this smoothing makes of independent point noise (``noise_mm`` per point, along the normal).

        Node i's value is about sum_p k_i(p) d_p / W_i over the points p of the cells j (n_j points each, kernel
        weight K_ij, W_i = sum_j K_ij n_j), so Cov(a_i, a_k) = noise^2 sum_j K_ij K_kj n_j / (W_i W_k): the node std
        is noise sqrt(sum_j K_ij^2 n_j) / W_i, times the square root of the plane fit's intercept inflation (one-sided
        support), and the correlation sum g_i = sum_k Cov_ik / (s_i s_k) takes two sparse products (no N x N matrix).
        """
        if not np.isfinite(noise_mm):
            return FieldErrorModel.none()
        with np.errstate(invalid="ignore", divide="ignore"):
            spread = np.sqrt(self.kernel_squared_ @ counts) / weight  # std per unit point noise, before inflation
            t = np.where(supported, 1.0 / (weight * spread), 0.0)  # 1 / (W_k s_k)
            correlation = t * (self.kernel_ @ (counts * (self.kernel_.T @ t)))
        std = np.where(supported, noise_mm * spread * np.sqrt(np.maximum(inflation, 1.0)), np.nan)
        return FieldErrorModel("scan", std, np.where(supported, np.maximum(correlation, 1.0), 1.0),
                               float(self.radius_mm_), bias_correlation=SMOOTHING_BIAS_CORRELATION)


_PREPARED: dict[tuple, ScanFieldEstimator] = {}


def prepared_estimator(skin: SkinSurface, **options: float | None) -> ScanFieldEstimator:
    """A fitted :class:`ScanFieldEstimator` for ``skin``, reused across calls with the same skin and options.

    The preparation (grid, kernel, quadrics) costs far more than one scan; callers that hold a skin for many scans
    (the scan node, the CLI) get it once. Keyed by ``model_id``, node count and the options; keeps the last 4.
    """
    key = (skin.model_id, skin.n_nodes, tuple(sorted(options.items())))
    if key not in _PREPARED:
        if len(_PREPARED) >= 4:
            _PREPARED.pop(next(iter(_PREPARED)))
        _PREPARED[key] = ScanFieldEstimator(**options).fit(skin)
    return _PREPARED[key]


def _check_points(points_mm: np.ndarray, skin: SkinSurface) -> np.ndarray:
    """Validate a raw scan (M, 3) mm; returns its finite rows. Raises ScanError naming the problem."""
    points = np.asarray(points_mm, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ScanError(f"scan points must be an (M, 3) array in mm; got shape {points.shape}")
    if points.shape[0] == 0:
        raise ScanError("scan is empty: 0 points")
    finite = np.isfinite(points[:, 0] + points[:, 1] + points[:, 2])  # any NaN or inf makes the sum non-finite
    if not finite.any():
        raise ScanError(f"scan has no finite points: all {points.shape[0]} points are NaN or infinite")
    if not finite.all():
        points = points[finite]
    # Unit check on robust extents: a part seen partly still spans a good fraction of its own size.
    lo, hi = np.percentile(points[:: max(1, points.shape[0] // 50000)], [1, 99], axis=0)
    scan_size = float(np.linalg.norm(hi - lo))
    skin_size = float(np.linalg.norm(np.ptp(skin.points, axis=0)))
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
        None: estimated from the marker residual.
    Returns the DisplacementField with its error model (node std and correlation of the smoothing, the marker
    registration's pose covariance) (paper: the condensed signed distance field) and the RegistrationResult.
    Raises ScanError for an empty or all-NaN scan, a scan in metres, no overlap with the part or too little coverage.
    """
    points = _check_points(points_mm, skin)
    est = estimator if estimator is not None else prepared_estimator(skin)
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
