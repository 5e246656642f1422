"""The block-wise scan path against a plain per-node reference, and its compiled path against its numpy path."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

from hood_decomp.core.scan import kernels, scan_field
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, warm_up
from hood_decomp.core.types import SkinSurface
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan
from tests.skins import along_normals, crowned_patch, smooth_field


@pytest.fixture(scope="module")
def skin() -> SkinSurface:
    return crowned_patch(41, 35, hole_radius_mm=110.0)


@pytest.fixture(scope="module")
def estimator(skin) -> ScanFieldEstimator:
    return ScanFieldEstimator().fit(skin)


@pytest.fixture(scope="module")
def scan_points(skin) -> np.ndarray:
    """A registered 0.05 mm scan with 2 % outliers (the second pass drops points) and some NaN rows, part frame."""
    truth = smooth_field(skin, amplitude_mm=1.0)
    scan = synthesize_scan(skin, along_normals(skin, truth),
                           ScannerConfig(n_points=60_000, noise_mm=0.05, outlier_fraction=0.02), 4)  # fmt: skip
    points = scan.points @ scan.true_transform[:3, :3].T + scan.true_transform[:3, 3]
    points[::997] = np.nan
    return points


def _in_a_fresh_interpreter(script: str) -> None:
    """Run ``script`` with ``python -c`` (the repository on the path); asserts it exits 0."""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]


def _weighted_plane(u: np.ndarray, v: np.ndarray, d: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Weighted least squares d = a + b u + c v by numpy's lstsq on sqrt(w)-scaled rows: coefficients, sum of
    weights, and the intercept's variance inflation sum(w) * (A^T W A)^-1_00."""
    design = np.column_stack([np.ones_like(u), u, v])
    root = np.sqrt(w)
    coef = np.linalg.lstsq(design * root[:, None], d * root, rcond=None)[0]
    normal = design.T @ (design * w[:, None])
    return coef, float(w.sum()), float(w.sum() * np.linalg.inv(normal)[0, 0])


def _reference_field(est: ScanFieldEstimator, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Node values and supported mask by the algorithm written out per node: for node i, every located point of every
    cell j with kernel weight K_ij, placed at x_j + u t1_j + v t2_j and expressed in node i's tangent frame, fitted
    by a weighted plane; then points with residual (to their own cell node's plane) beyond outlier_sigma robust
    standard deviations dropped, and refitted; with twicing, the kept points' residuals from their own cell node's
    plane fitted the same way and the fit added."""
    located = est.point_distances(points)
    on = np.flatnonzero(located.node >= 0)
    node, u, v, d = located.node[on], located.tangent[on, 0], located.tangent[on, 1], located.distance[on]
    # the stored precision of the per-point values (float32), as the estimator keeps them
    u, v, d = (a.astype(np.float32).astype(np.float64) for a in (u, v, d))
    frames, x = est.frames_, est.points_
    position = x[node] + u[:, None] * frames[node, 0] + v[:, None] * frames[node, 1]
    kernel = est.kernel_.tocsr()
    members = [np.flatnonzero(node == j) for j in range(x.shape[0])]
    n = x.shape[0]

    def fit(keep: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        coef, weight, inflation = np.full((n, 3), np.nan), np.zeros(n), np.full(n, np.inf)
        for i in range(n):
            cols = kernel.indices[kernel.indptr[i] : kernel.indptr[i + 1]]
            vals = kernel.data[kernel.indptr[i] : kernel.indptr[i + 1]]
            rows = [members[j][keep[members[j]]] for j in cols]
            w = np.concatenate([np.full(r.size, k) for r, k in zip(rows, vals, strict=True)])
            rows = np.concatenate(rows)
            if rows.size < 3:
                continue
            rel = position[rows] - x[i]
            coef[i], weight[i], inflation[i] = _weighted_plane(rel @ frames[i, 0], rel @ frames[i, 1], d[rows], w)
        return coef, weight, inflation

    everything = np.ones(node.size, bool)
    coef, _, _ = fit(everything, d)
    residual = d - (coef[node, 0] + coef[node, 1] * u + coef[node, 2] * v)
    sigma = 1.4826 * np.median(np.abs(residual[np.isfinite(residual)]))
    keep = ~(np.abs(residual) > est.outlier_sigma * sigma)
    coef, weight, inflation = fit(keep, d)
    if est.twicing_:  # the same fit of every kept point's residual from its own node's plane (none: the distance)
        own = np.nan_to_num(coef[node])
        twice, _, _ = fit(keep, d - (own[:, 0] + own[:, 1] * u + own[:, 2] * v))
        coef = coef + twice
    counts = np.array([np.count_nonzero(keep[m]) for m in members], dtype=float)
    nearby = (kernel >= 0.75**2).astype(float) @ counts  # nodes within half the radius: biweight >= (1 - 0.5^2)^2
    supported = ((weight >= est.min_points) & (inflation <= est.max_inflation)
                 & (nearby >= max(1.0, est.min_points / 4)) & np.isfinite(coef[:, 0]))  # fmt: skip
    return coef[:, 0], supported


def test_field_equals_a_per_node_reference(estimator, scan_points):
    """Fails if the fused binning, the raw-moment mixing, the closed-form 3x3 fits, the outlier pass or the twicing
    pass (from cell sums) of the block path compute anything but the per-node weighted plane fits written out
    plainly (to 1e-9 mm)."""
    assert estimator.twicing_  # the patch's 89 mm radius is above TWICING_MIN_RADIUS_MM
    expected, supported = _reference_field(estimator, scan_points)
    field = estimator.field(scan_points)
    value = field.normal_displacement
    assert supported.sum() > 0.8 * supported.size
    np.testing.assert_array_equal(np.isfinite(value), supported)
    np.testing.assert_allclose(value[supported], expected[supported], rtol=0, atol=1e-9)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed: only the numpy path exists")
def test_compiled_path_equals_the_numpy_path(estimator, scan_points, monkeypatch):
    """Fails if the compiled kernels and the numpy path differ by more than 1e-9 mm anywhere (values, node std,
    noise) or their correlation sums by more than 1e-9 relative, with a transform folded in, several threads and
    blocks of points and of nodes, NaN rows and outliers."""
    monkeypatch.setattr(kernels, "NODE_BLOCK", 500)  # the patch's 1,405 nodes in three blocks on the numpy path
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation.T, [5.0, -3.0, 2.0]
    scanner = (scan_points - transform[:3, 3]) @ rotation.T  # the same points in a scanner frame
    many = np.concatenate([scanner] * 5)  # more than one block, two threads
    fields = []
    for compiled in (True, False):
        previous = kernels.use_compiled(compiled)
        try:
            assert kernels.compiled() is compiled
            fields.append(estimator.field(many, transform))
            located = estimator._scan_points(many, transform, moments=True, workers=2)
        finally:
            kernels.use_compiled(previous)
        fields.append(located)
    fast, fast_located, slow, slow_located = fields
    for a, b in zip(fast_located[:5], slow_located[:5], strict=True):  # rows, nodes, u, v, d: bit for bit
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(fast_located[5], slow_located[5], rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(np.isnan(fast.normal_displacement), np.isnan(slow.normal_displacement))
    np.testing.assert_allclose(fast.normal_displacement, slow.normal_displacement, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.error_model.node_std, slow.error_model.node_std, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast.error_model.correlation, slow.error_model.correlation, rtol=1e-9, atol=0)
    assert abs(fast.noise_rms - slow.noise_rms) < 1e-9
    assert np.isfinite(fast.normal_displacement).mean() > 0.8


def test_warm_up_leaves_the_estimator_unchanged(skin, scan_points):
    """Fails if warming the scan path up (the scan node does it before it serves) changes any later field, or if it
    fails on a fitted estimator."""
    estimator = ScanFieldEstimator().fit(skin)
    before = estimator.field(scan_points)
    warm_up(estimator)
    after = estimator.field(scan_points)
    np.testing.assert_array_equal(after.normal_displacement, before.normal_displacement)
    np.testing.assert_array_equal(after.error_model.node_std, before.error_model.node_std)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed: only the numpy path exists")
def test_first_compiled_use_from_many_threads_at_once():
    """Fails if the first use of the compiled kernels from several threads at once (a node's first scan runs in
    threads) compiles them twice and raises (a fresh interpreter, eight threads released together)."""
    _in_a_fresh_interpreter(
        "import threading\n"
        "from hood_decomp.core.scan import kernels\n"
        "barrier = threading.Barrier(8)\n"
        "errors = []\n"
        "def first():\n"
        "    barrier.wait()\n"
        "    try:\n"
        "        kernels._kernel('_locate_block_loop')\n"
        "    except Exception as error:\n"
        "        errors.append(repr(error))\n"
        "threads = [threading.Thread(target=first) for _ in range(8)]\n"
        "[t.start() for t in threads]\n"
        "[t.join() for t in threads]\n"
        "assert not errors, errors\n"
    )


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed: only the numpy path exists")
def test_a_fresh_process_loads_numba_for_large_scans_and_after_a_warm_up_only():
    """Fails if a fresh process loads numba for a scan below COMPILED_MIN_POINTS (a one-off run pays ~0.6 s of CPU
    for nothing), if a scan at the threshold does not take the compiled path, or if a node's warm-up leaves later
    small scans on the numpy path (the node would then serve them about 3 times slower)."""
    _in_a_fresh_interpreter(
        "import sys\n"
        "from hood_decomp.core.scan import kernels\n"
        "from hood_decomp.core.scan.scan_field import ScanFieldEstimator, warm_up\n"
        "from tests.skins import crowned_patch\n"
        "estimator = ScanFieldEstimator().fit(crowned_patch(21, 17))\n"
        "estimator.field(estimator.points_ + 0.01 * estimator.frames_[:, 2])\n"
        "assert 'numba' not in sys.modules, 'a small scan loaded numba'\n"
        "assert not kernels.for_points(kernels.COMPILED_MIN_POINTS - 1)\n"
        "assert kernels.for_points(kernels.COMPILED_MIN_POINTS)\n"
        "warm_up(estimator, points=20_000)\n"
        "assert 'numba' in sys.modules and kernels.for_points(10), 'the warm-up did not load the compiled path'\n"
    )


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.skipif(
    not kernels.HAVE_NUMBA, reason="numba is not installed: only the numpy path exists"))])
def test_the_fused_second_pass_drops_and_sums_what_a_residual_array_would(compiled):
    """The second pass splits points by residual without forming a residual array (kernels.outliers). Fails if it
    drops other points than those whose float32 residual exceeds the limit in magnitude, or if its inlier count or
    sum of squares differs from those of the finite, kept residuals computed as one array in plain numpy (more than
    one block, NaN planes, an infinite one)."""
    rng = np.random.default_rng(3)
    n, m = 500, 3 * kernels.BLOCK_POINTS + 17
    coef = rng.normal(0.0, 0.2, (n, 3))
    coef[7] = np.nan  # a node without a fit: its points' residuals are NaN, neither dropped nor counted
    coef[11, 0] = np.inf  # an infinite one: dropped
    j = rng.integers(0, n, m).astype(np.int32)
    u, v = (rng.uniform(-2.0, 2.0, m).astype(np.float32) for _ in range(2))
    d = (rng.normal(0.0, 0.05, m) + np.where(rng.random(m) < 0.01, 1.0, 0.0)).astype(np.float32)
    residual = (d.astype(float) - (coef[j, 0] + coef[j, 1] * u.astype(float) + coef[j, 2] * v.astype(float)))
    residual = residual.astype(np.float32).astype(float)  # stored as float32, as plane_residuals does
    limit = 0.2
    with np.errstate(invalid="ignore"):
        expected_drop = np.flatnonzero(np.abs(residual) > limit)
        kept = residual[np.isfinite(residual) & ~(np.abs(residual) > limit)]
    previous = kernels.use_compiled(compiled)
    try:
        drop, inliers, squares = kernels.outliers(j, u, v, d, coef, limit, compiled)
    finally:
        kernels.use_compiled(previous)
    np.testing.assert_array_equal(drop, expected_drop)
    assert inliers == kept.size and 0 < inliers < m - drop.size
    assert squares == pytest.approx(float(np.sum(kept * kept)), rel=1e-12)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.skipif(
    not kernels.HAVE_NUMBA, reason="numba is not installed: only the numpy path exists"))])
def test_the_kernel_pass_equals_sparse_products(estimator, compiled):
    """kernels.kernel_sums walks the CSR kernel once instead of keeping a transposed, squared and thresholded copy.
    Fails if its column subtraction differs from scipy's K[:, rows] @ removed (the kernel is not symmetric, so K's
    rows would give other numbers), or its squared-kernel or near sums from scipy's products with K * K and with
    K >= 0.5625, on the estimator's own kernel (five copies of it: more than one block of the numpy path)."""
    kernel = sp.block_diag([estimator.kernel_] * 5, format="csr")  # five copies: more than one block
    n = kernel.shape[0]
    assert abs(kernel - kernel.T).max() > 0.1 and kernel.nnz > kernels.BLOCK_POINTS
    assert len(kernels.row_parts(kernel.indptr, 2)) == 2  # the compiled loop: two runs of rows on two threads
    rng = np.random.default_rng(5)
    counts = rng.integers(0, 20, n).astype(float)
    rows = np.sort(rng.choice(n, 200, replace=False))
    removed = rng.normal(0.0, 1.0, (rows.size, 14))
    mixed = rng.normal(0.0, 1.0, (n, 14))
    expected = mixed - kernel.tocsc()[:, rows] @ removed
    previous = kernels.use_compiled(compiled)
    try:
        squared, nearby = kernels.kernel_sums(kernel.indptr, kernel.indices, kernel.data, counts, rows, removed,
                                              0.75**2, mixed, compiled)  # fmt: skip
    finally:
        kernels.use_compiled(previous)
    np.testing.assert_allclose(mixed, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(squared, kernel.multiply(kernel) @ counts, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(nearby, (kernel >= 0.75**2).astype(float) @ counts)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.skipif(
    not kernels.HAVE_NUMBA, reason="numba is not installed: only the numpy path exists"))])
def test_the_error_model_sums_equal_dense_products_of_the_equivalent_weights(estimator, scan_points, compiled,
                                                                              monkeypatch):
    """The scan error model's weights: node i's intercept is linear in its points' distances, a_i = sum over the
    kernel-weighted points of d (c_i + w_i . p) (p about the skin centroid), so kernels.node_fits' rows [c_i, w_i]
    must give the fitted intercept from the mixed moments [sum d, sum d p]; kernels.covariance_sums forms t (A D A^T t)
    without an N x N matrix (A = L or 2 L - L L, L_ij = K_ij (c_i n_j + w_i . P_j)) and kernels.twiced_variance the
    diagonals of L D L^T and A D A^T. Fails if the rows are not the fit's equivalent kernel (a wrong sign, frame or
    inverse row: 1e-9 relative on the patch scan's intercepts), or if either sum differs by more than 1e-9 relative
    from dense products (a transposed product taken the wrong way round: K is not symmetric; a dropped L L term;
    cells without points, where D is 0, or t = 0 mishandled; a numpy twin computing something else). The kernel's
    products (ScanFieldEstimator._smooth) run by blocks of rows on threads (kernels.row_parts): here three, so a
    block's rows lost or written to another block's place fail too."""
    n = estimator.points_.shape[0]
    previous = kernels.use_compiled(compiled)
    try:
        cells = estimator._scan_points(scan_points, moments=True, fast=compiled, rows=False)[5]
        raw = estimator._raw_moments(cells, np.arange(n), compiled)
        mixed = estimator.kernel_ @ raw
        coef, _, _, rows = estimator._node_fits(mixed, compiled, equivalent=True)
        fitted = np.isfinite(coef[:, 0])
        intercept = rows[:, 0] * mixed[:, 10] + np.einsum("nd,nd->n", rows[:, 1:], mixed[:, 11:14])
        np.testing.assert_allclose(intercept[fitted], coef[fitted, 0], rtol=1e-9, atol=1e-9)
        rng = np.random.default_rng(9)
        rows = rows * rng.uniform(0.5, 1.5, (n, 1))  # other numbers through the same algebra
        raw[rng.random(n) < 0.1, :4] = 0.0  # cells without points
        t = rng.uniform(0.5, 2.0, n) * (rng.random(n) > 0.1)
        kernel = estimator.kernel_
        weights = kernel.toarray() * (rows[:, :1] * raw[None, :, 0] + rows[:, 1:] @ raw[:, 1:4].T)
        inverse = np.diag(np.where(raw[:, 0] > 0, 1.0 / np.maximum(raw[:, 0], 1.0), 0.0))
        twiced_weights = 2.0 * weights - weights @ weights
        args = (kernel.indptr, kernel.indices, kernel.data, rows, raw)
        monkeypatch.setattr(kernels, "BLOCK_POINTS", kernel.nnz // 4)  # parts of at least this many entries
        assert len(kernels.row_parts(kernel.indptr, 3)) == 3
        monkeypatch.setattr(estimator, "kernel_blocks_", scan_field._row_blocks(kernel, 3))
        np.testing.assert_array_equal(estimator._smooth(raw), kernel @ raw)
        for twiced, a in ((False, weights), (True, twiced_weights)):
            got = kernels.covariance_sums(*args, t, twiced, compiled)
            np.testing.assert_allclose(got, t * (a @ inverse @ a.T @ t), rtol=1e-9, atol=1e-9 * np.abs(got).max())
        plain, twiced = kernels.twiced_variance(*args, compiled)
    finally:
        kernels.use_compiled(previous)
    np.testing.assert_allclose(plain, np.diag(weights @ inverse @ weights.T), rtol=1e-9, atol=0)
    np.testing.assert_allclose(twiced, np.diag(twiced_weights @ inverse @ twiced_weights.T), rtol=1e-9, atol=0)


def test_triangle_areas_by_blocks_are_the_analytic_areas():
    """SkinSurface.triangle_areas goes by blocks of 65,536 triangles with the cross product by components (the scan
    step's bias correlation and the within-model test's nodal areas use it). Fails if a block is skipped, shifted or
    mixed up, or a component of the cross product is wrong: 200,000 right triangles of known legs in every
    orientation (area = legs' product / 2)."""
    rng = np.random.default_rng(8)
    count = 200_000
    legs = rng.uniform(0.5, 5.0, (count, 2))
    rotation = np.linalg.qr(rng.normal(size=(count, 3, 3)))[0]  # a random orthonormal frame per triangle
    origin = rng.uniform(-100.0, 100.0, (count, 3))
    corners = np.stack([origin, origin + legs[:, :1] * rotation[:, 0], origin + legs[:, 1:] * rotation[:, 1]], axis=1)
    skin = SkinSurface(corners.reshape(-1, 3), np.tile([0.0, 0.0, 1.0], (3 * count, 1)),
                       np.arange(3 * count).reshape(count, 3), "triangles")  # fmt: skip
    np.testing.assert_allclose(skin.triangle_areas(), legs[:, 0] * legs[:, 1] / 2, rtol=1e-9)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed: only the numpy path exists")
def test_a_cloud_in_no_spatial_order_is_sorted_by_tiles_the_same_way_on_both_paths(estimator, scan_points):
    """Fails if a scanned cloud (line order) is copied or reordered, if a shuffled one is not sorted into tiles of
    TILE_CELLS grid cells (checked against tile indices computed here from the grid's origin and cell), if points are
    lost, duplicated or altered by the sort, if the two paths order differently, or if the field of the shuffled
    cloud is not the field of the scanned one (to 1e-9 mm: below 100k points every residual enters the noise scale,
    so nothing but the summation order differs)."""
    affine, hi = estimator._grid_map(None)
    cell = estimator.grid_cell_mm_
    shuffled = scan_points[np.random.default_rng(7).permutation(scan_points.shape[0])]
    for fast in (True, False):
        assert kernels.tile_order(scan_points, affine, hi, cell, fast) is scan_points
    fast, slow = (kernels.tile_order(shuffled, affine, hi, cell, path) for path in (True, False))
    np.testing.assert_array_equal(fast, slow)
    last = np.floor(hi / kernels.TILE_CELLS)
    tiles = np.clip(np.floor((fast - estimator.grid_origin_) / cell / kernels.TILE_CELLS), 0, last)
    tiles[np.isnan(tiles)] = 0
    key = (tiles[:, 0] * (last[1] + 1) + tiles[:, 1]) * (last[2] + 1) + tiles[:, 2]
    assert np.all(np.diff(key) >= 0) and np.unique(key).size > 10
    np.testing.assert_array_equal(np.unique(fast, axis=0), np.unique(shuffled, axis=0))
    assert np.isnan(fast).any(axis=1).sum() == np.isnan(shuffled).any(axis=1).sum()
    scanned, sorted_ = (estimator.field(points).normal_displacement for points in (scan_points, shuffled))
    np.testing.assert_array_equal(np.isfinite(scanned), np.isfinite(sorted_))
    assert np.nanmax(np.abs(scanned - sorted_)) < 1e-9


def _plain_nearest_node_grid(est: ScanFieldEstimator) -> np.ndarray:
    """The estimator's grid (origin, cell, shape) as a plain (S0, S1, S2) table of the node in the nearest node cell
    (scipy's exact distance transform, the last node of a cell written wins): the lookup before the bricks."""
    from scipy import ndimage

    keys = np.floor((est.points_ - est.grid_origin_) / est.grid_cell_mm_).astype(np.int64)
    table = np.full(tuple(est.grid_shape_), -1, np.int64)
    table[keys[:, 0], keys[:, 1], keys[:, 2]] = np.arange(est.points_.shape[0])
    nearest = ndimage.distance_transform_edt(table < 0, return_distances=False, return_indices=True)
    return table[tuple(nearest)]


@pytest.mark.parametrize("normal_axis", [2, 0])
@pytest.mark.parametrize("compiled", [True, False] if kernels.HAVE_NUMBA else [False])
def test_the_bricked_table_finds_each_points_node_of_the_plain_grid(skin, scan_points, normal_axis, compiled):
    """Fails if a point's cell is read from the wrong entry of the bricked table (kernels.grid_layout, brick_order):
    every point, on the skin, off it, outside the grid or NaN, must be located (node, u, v, d) exactly as a lookup of
    the plain nearest-node grid followed by the gates written out here, on both paths; and for a skin whose normals
    point along x instead of z, whose bricks lie across x."""
    order = [(k + 2 - normal_axis) % 3 for k in range(3)]  # z to axis normal_axis, cyclically: a rotation
    turned = SkinSurface(skin.points[:, order], skin.normals[:, order], skin.triangles, skin.model_id)
    est = ScanFieldEstimator().fit(turned)
    brick = np.full(3, scan_field.GRID_BRICK)
    brick[normal_axis] = 1
    np.testing.assert_array_equal(est.grid_brick_, brick)
    assert np.all(est.grid_shape_ % brick == 0) and est.grid_table_.size == np.prod(est.grid_shape_)
    rng = np.random.default_rng(5)
    lo, hi = est.grid_origin_, est.grid_origin_ + est.grid_shape_ * est.grid_cell_mm_
    box = rng.uniform(lo - 30.0, hi + 30.0, (20_000, 3))  # everywhere in the grid and around it
    points = np.concatenate([scan_points[:, order], box])
    previous = kernels.use_compiled(compiled)
    try:
        located = est.point_distances(points)
    finally:
        kernels.use_compiled(previous)
    cells = np.floor((points - est.grid_origin_) / est.grid_cell_mm_)
    cells = np.clip(np.nan_to_num(cells, nan=0.0), 0, est.grid_shape_ - 1).astype(np.int64)
    j = _plain_nearest_node_grid(est)[cells[:, 0], cells[:, 1], cells[:, 2]]
    offset = points - est.points_[j]
    u, v, w = (np.einsum("md,md->m", offset, est.frames_[j, k]) for k in range(3))
    q = est.quadric_[j]
    d = w - (q[:, 0] * u + q[:, 1] * v + q[:, 2] * u * u + q[:, 3] * u * v + q[:, 4] * v * v)
    with np.errstate(invalid="ignore"):
        passed = (np.abs(d) <= est.max_distance_mm) & (u * u + v * v <= est.gate2_[j])
    assert 0.3 * points.shape[0] < passed.sum() < points.shape[0] - 20_000  # on the skin and off it, both
    np.testing.assert_array_equal(located.node, np.where(passed, j, -1))
    np.testing.assert_allclose(located.distance[passed], d[passed], rtol=0, atol=1e-4)  # float32 storage
    np.testing.assert_allclose(located.tangent[passed], np.column_stack([u, v])[passed], rtol=0, atol=1e-3)
