"""The scan path's per-point and per-node loops, compiled with numba where it is installed, in numpy otherwise.

Both paths do the same arithmetic in the same order (float64 throughout, the located u, v, d stored as float32 and
the cell sums taken of those stored values), so they give the same field to rounding (test: 1e-9 mm). The numpy
path is chosen with ``HOOD_DECOMP_PURE_NUMPY=1`` or when numba is missing; :func:`use_compiled` switches at run time.
By default (``use_compiled(None)``) a scan takes the compiled path when the kernels are loaded in this process
already (:func:`load`: a node's warm-up) or when it has at least ``COMPILED_MIN_POINTS`` points (:func:`for_points`).
In a fresh process (a one-off ``estimate --scan``) numba costs about 0.3 s of CPU to import and load its cache and
another 0.3 s at exit (LLVM's teardown); the numpy path costs about 0.45 s of CPU more per million points, in
threads that share the GIL where the compiled loops do not. Whole one-off runs measured (benchmarks/RESULTS.md,
issue 19): at 1 M points the numpy path took 0.3-0.5 s less CPU, at 5 M the two were even.

Per point (:func:`locate_block`): grid coordinates from one affine map, the cell's node (a table laid out in
bricks, :func:`grid_layout`), the offset in the node's frame, the quadric distance, the gates; the points that pass
are written to preallocated block buffers and (when ``cells`` is given) their moments [1, u, v, uu, uv, vv, d, du,
dv] are added to their node's cell sums, in one pass.
Per node (:func:`raw_moments`, :func:`node_fits`): the cell sums to raw 3D moments (the second moments formed from
the node's basis rows, :func:`_second_moments`: no per-node map stored), and the closed-form 3x3 plane fit. The
second pass (:func:`outliers`): residuals, outliers and the noise sums in one pass, without an array of the scan's
size; then (:func:`kernel_sums`) one pass over the node kernel takes the dropped points back out of the mixed
moments and sums what the support test and the error model need, so that no transposed, squared or thresholded copy
of the kernel is built when a process starts (those took 0.2 s of CPU and 90 MB in a one-off run at paper
resolution). The error model's correlation sums (:func:`covariance_sums`) go over the kernel two or four more times
with the plane fit's equivalent weights made as they are used; :func:`twiced_variance` (once per skin) takes the
kernel's two-ring product. The compiled loops get the index arrays as unsigned views (:func:`_unsigned`).
"""

from __future__ import annotations

import importlib.util
import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

#: numba is optional (the numpy path gives the same numbers) and imported only when a kernel first runs: it costs
#: about 0.3 s of start-up that a verb without scans need not pay
HAVE_NUMBA = importlib.util.find_spec("numba") is not None
#: points per block: a block's temporaries on the numpy path (the gathered (B, 18) node rows and about 20 float64
#: columns: 20 MB per thread at 131,072 points) are made fresh in a one-off process; 65,536 took as little CPU per
#: scan and 30 MB less memory (paper 1M, benchmarks/RESULTS.md, 2026-11-24); the compiled path does not care
BLOCK_POINTS = 65_536
#: nodes per block of the numpy path's per-node steps (raw moments, plane fits): their two dozen (K,) temporaries stay
#: in cache and are not made fresh at the skin's size (N = 189k at paper resolution: 1.5 MB each)
NODE_BLOCK = 16_384
#: a scan of at least this many points loads the compiled kernels when they are not loaded yet (module docstring)
COMPILED_MIN_POINTS = 2_000_000
#: grid cells per edge of the tiles a cloud in no spatial order is sorted by (:func:`tile_order`: at paper resolution
#: 8 cells, 31 mm, sorted a shuffled 1M cloud in half the time of 2 cells and ran it as fast as 2), and the median
#: step between consecutive points, in grid cells, above which a cloud counts as in no spatial order: a scanner's
#: points follow its lines (median step about one point spacing, under a grid cell); a shuffled, voxel-hashed or
#: merged-by-hash cloud jumps across the part (hundreds of cells)
TILE_CELLS = 8
UNORDERED_STEP_CELLS = 8.0
#: True: compiled path, False: numpy path, None: by size (:func:`for_points`)
_MODE: bool | None = None if HAVE_NUMBA and os.environ.get("HOOD_DECOMP_PURE_NUMPY", "") not in ("1", "true",
                                                                                                 "yes") else False
_JIT: dict[str, object] = {}
_JIT_LOCK = threading.Lock()


def use_compiled(enabled: bool | None) -> bool | None:
    """Select the compiled (True, if numba is installed) or the numpy path (False) for every scan, or the choice by
    size (None, the default; :func:`for_points`); returns the previous setting."""
    global _MODE
    previous = _MODE
    _MODE = None if enabled is None and HAVE_NUMBA else bool(enabled) and HAVE_NUMBA
    return previous


def compiled() -> bool:
    """Whether the compiled path may be used (forced, or chosen by size)."""
    return _MODE is not False


def load() -> bool:
    """Make the compiled path this process's choice for every later scan, whatever its size (for a long-lived
    process: the scan node's warm-up): numba is imported and the loops prepared (read from numba's cache, or
    compiled, at their first run). Returns False when the compiled path is switched off or numba is missing."""
    if _MODE is False:
        return False
    _kernel("_locate_block_loop")
    return True


def for_points(points: int) -> bool:
    """Whether a scan of ``points`` points takes the compiled path: as set by :func:`use_compiled`, else when the
    compiled kernels are loaded already or ``points`` >= ``COMPILED_MIN_POINTS``."""
    if _MODE is None:
        return bool(_JIT) or points >= COMPILED_MIN_POINTS
    return _MODE


# --------------------------------------------------------------------------------------------------- numpy path
def _locate_block_numpy(points, start, stop, affine, hi, layout, table, cell_mm, nodes, max_d,
                        out_row, out_j, out_u, out_v, out_d, cells):  # fmt: skip
    x, y, z = points[start:stop, 0], points[start:stop, 1], points[start:stop, 2]
    g = [x * affine[k, 0] + y * affine[k, 1] + z * affine[k, 2] + affine[k, 3] for k in range(3)]
    flat = np.zeros(stop - start, np.int64)
    for k in range(3):
        index = np.floor(g[k])
        np.fmax(index, 0.0, out=index)  # fmax/fmin, unlike clip, also send NaN to a border cell
        np.fmin(index, hi[k], out=index)
        cell = index.astype(np.int64)
        flat += (cell >> layout[k, 0]) * layout[k, 2] + (cell & layout[k, 1]) * layout[k, 3]
    j = table[flat]
    # one gather (take: a fifth less CPU than nodes[j]): node position in grid units (3), frame rows t1, t2, n (9),
    # quadric (5), gate (1)
    node = np.take(nodes, j, axis=0)
    o0, o1, o2 = ((g[k] - node[:, k]) * cell_mm for k in range(3))
    u = node[:, 3] * o0 + node[:, 4] * o1 + node[:, 5] * o2
    v = node[:, 6] * o0 + node[:, 7] * o1 + node[:, 8] * o2
    w = node[:, 9] * o0 + node[:, 10] * o1 + node[:, 11] * o2
    d = w - (node[:, 12] * u + node[:, 13] * v + node[:, 14] * u * u + node[:, 15] * u * v + node[:, 16] * v * v)
    with np.errstate(invalid="ignore"):
        ok = np.flatnonzero((np.abs(d) <= max_d) & (u * u + v * v <= node[:, 17]))
    count = ok.size
    out_row[:count] = ok + start
    out_j[:count] = j[ok]
    out_u[:count] = u[ok]
    out_v[:count] = v[ok]
    out_d[:count] = d[ok]
    if cells is not None:
        _add_moments_numpy(out_j[:count], out_u[:count], out_v[:count], out_d[:count], 1.0, cells)
    return count


def _tile_keys(points, affine, hi, tile):
    """(M,) int64 tile index of each point: grid units by the affine, divided by ``tile`` cells, floored and clamped
    as :func:`_cell` does (NaN to tile 0), x-major."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    keys = np.zeros(points.shape[0], np.int64)
    for k in range(3):  # the grid units as locate_block forms them, bit for bit
        index = np.floor((x * affine[k, 0] + y * affine[k, 1] + z * affine[k, 2] + affine[k, 3]) / tile)
        np.fmax(index, 0.0, out=index)
        np.fmin(index, hi[k], out=index)
        keys = keys * (np.int64(hi[k]) + 1) + index.astype(np.int64)
    return keys


def _tile_order_numpy(points, affine, hi, tile, counts, out):
    out[:] = points[np.argsort(_tile_keys(points, affine, hi, tile), kind="stable")]


def _add_moments_numpy(j, u32, v32, d32, sign, cells):
    n = cells.shape[0]
    j = j.astype(np.intp)  # once, not in each bincount
    u, v, d = u32.astype(np.float64), v32.astype(np.float64), d32.astype(np.float64)
    columns = (lambda: None, lambda: u, lambda: v, lambda: u * u, lambda: u * v, lambda: v * v, lambda: d,
               lambda: d * u, lambda: d * v)  # made one at a time  # fmt: skip
    for k, column in enumerate(columns):
        sums = np.bincount(j, weights=column(), minlength=n)
        if sign > 0:
            cells[:, k] += sums
        else:
            cells[:, k] -= sums


def _plane_residuals_numpy(j, u, v, d, coef, out):
    for start in range(0, j.size, BLOCK_POINTS):
        part = slice(start, start + BLOCK_POINTS)
        c = coef[j[part]]
        out[part] = d[part] - (c[:, 0] + c[:, 1] * u[part] + c[:, 2] * v[part])


def _outliers_numpy(j, u, v, d, coef, limit, out_drop):
    count, inliers, squares = 0, 0, 0.0
    residual = np.empty(min(j.size, BLOCK_POINTS), np.float32)
    for start in range(0, j.size, BLOCK_POINTS):
        part = slice(start, start + BLOCK_POINTS)
        r = residual[: j[part].size]
        _plane_residuals_numpy(j[part], u[part], v[part], d[part], coef, r)
        r = r.astype(np.float64)
        outlier = np.abs(r) > limit
        found = np.flatnonzero(outlier)
        out_drop[count : count + found.size] = found + start
        count += found.size
        kept = r[np.isfinite(r) & ~outlier]
        inliers, squares = inliers + kept.size, squares + float(np.sum(kept * kept))  # not BLAS (its threads)
    return count, inliers, squares


def _second_moments(n, u, v, uu, uv, vv, x, t1, t2):
    """The upper triangle (xx xy xz yy yz zz) of sum p p^T over a cell's points p = x + u t1 + v t2 from its sums
    n, u, v, uu, uv, vv and its node's basis rows x (about the centroid), t1, t2: sum_e row_e g_e^T with
    g = (n x + u t1 + v t2, u x + uu t1 + uv t2, v x + uv t1 + vv t2). Formed per node (no (N, 6, 6) map: 54 MB at
    paper resolution). Elementwise: rows indexable by component, (3, K) arrays on the numpy path, (3,) compiled."""
    g0 = (n * x[0] + u * t1[0] + v * t2[0], n * x[1] + u * t1[1] + v * t2[1], n * x[2] + u * t1[2] + v * t2[2])
    g1 = (u * x[0] + uu * t1[0] + uv * t2[0], u * x[1] + uu * t1[1] + uv * t2[1], u * x[2] + uu * t1[2] + uv * t2[2])
    g2 = (v * x[0] + uv * t1[0] + vv * t2[0], v * x[1] + uv * t1[1] + vv * t2[1], v * x[2] + uv * t1[2] + vv * t2[2])
    return (x[0] * g0[0] + t1[0] * g1[0] + t2[0] * g2[0], x[0] * g0[1] + t1[0] * g1[1] + t2[0] * g2[1],
            x[0] * g0[2] + t1[0] * g1[2] + t2[0] * g2[2], x[1] * g0[1] + t1[1] * g1[1] + t2[1] * g2[1],
            x[1] * g0[2] + t1[1] * g1[2] + t2[1] * g2[2], x[2] * g0[2] + t1[2] * g1[2] + t2[2] * g2[2])


def _tangent_forms(s, t1, t2):
    """t1^T S t1, t1^T S t2, t2^T S t2 of the symmetric S given by its upper triangle s (xx xy xz yy yz zz).
    Elementwise as :func:`_second_moments`."""
    a = (s[0] * t1[0] + s[1] * t1[1] + s[2] * t1[2], s[1] * t1[0] + s[3] * t1[1] + s[4] * t1[2],
         s[2] * t1[0] + s[4] * t1[1] + s[5] * t1[2])  # S t1
    b = (s[0] * t2[0] + s[1] * t2[1] + s[2] * t2[2], s[1] * t2[0] + s[3] * t2[1] + s[4] * t2[2],
         s[2] * t2[0] + s[4] * t2[1] + s[5] * t2[2])  # S t2
    return (t1[0] * a[0] + t1[1] * a[1] + t1[2] * a[2], t1[0] * b[0] + t1[1] * b[1] + t1[2] * b[2],
            t2[0] * b[0] + t2[1] * b[1] + t2[2] * b[2])


def _plane_system(s0, ts0, ts1, q0, q1, q2, d0, td0, td1, a, b):
    """One node's plane-fit normal equations in its tangent frame from raw moments about the centroid (node offset
    a = t1.x, b = t2.x), solved by the adjugate: cofactors c00..c22, determinant, m00 m11 m22 (the singularity scale)
    and the right-hand side. Elementwise: numpy arrays on the numpy path, scalars in the compiled loop."""
    m00 = s0
    m01 = ts0 - s0 * a
    m02 = ts1 - s0 * b
    m11 = q0 - 2 * ts0 * a + s0 * a * a
    m12 = q1 - ts0 * b - a * ts1 + s0 * a * b
    m22 = q2 - 2 * ts1 * b + s0 * b * b
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    det = m00 * c00 + m01 * c01 + m02 * c02
    return (c00, c01, c02, m00 * m22 - m02 * m02, m01 * m02 - m00 * m12, m00 * m11 - m01 * m01, det, m00 * m11 * m22,
            d0, td0 - d0 * a, td1 - d0 * b)  # fmt: skip


def _raw_moments_numpy(cells, basis, rows):
    out = np.empty((rows.size, 14))
    every = rows.size == cells.shape[0] and np.array_equal(rows, np.arange(rows.size))
    for start in range(0, rows.size, NODE_BLOCK):
        part = slice(start, start + NODE_BLOCK)
        c = (cells[part] if every else cells[rows[part]]).T.copy()  # (9, K) and (3, 3, K): contiguous per component
        b = (basis[part] if every else basis[rows[part]]).transpose(1, 2, 0).copy()
        block = out[part]
        block[:, 0] = c[0]
        for dim in range(3):
            block[:, 1 + dim] = c[0] * b[0, dim] + c[1] * b[1, dim] + c[2] * b[2, dim]
            block[:, 11 + dim] = c[6] * b[0, dim] + c[7] * b[1, dim] + c[8] * b[2, dim]
        for col, value in enumerate(_second_moments(*c[:6], b[0], b[1], b[2])):
            block[:, 4 + col] = value
        block[:, 10] = c[6]
    return out


def _node_fits_numpy(mixed, frames, t1x, t2x, coef, weight, inflation, rows):
    for start in range(0, mixed.shape[0], NODE_BLOCK):
        part = slice(start, start + NODE_BLOCK)
        _node_fits_block(mixed[part], frames[part], t1x[part], t2x[part], coef[part], weight[part], inflation[part],
                         None if rows is None else rows[part])


def _node_fits_block(mixed, frames, t1x, t2x, coef, weight, inflation, rows):
    s0, s1, d0, d1 = mixed[:, 0], mixed[:, 1:4], mixed[:, 10], mixed[:, 11:14]
    ts = np.einsum("nkd,nd->nk", frames[:, :2], s1)
    td = np.einsum("nkd,nd->nk", frames[:, :2], d1)
    tangents = frames[:, :2].transpose(1, 2, 0).copy()  # contiguous per component
    quad = _tangent_forms(mixed[:, 4:10].T.copy(), tangents[0], tangents[1])
    c00, c01, c02, c11, c12, c22, det, scale, r0, r1, r2 = _plane_system(
        s0, ts[:, 0], ts[:, 1], quad[0], quad[1], quad[2], d0, td[:, 0], td[:, 1], t1x, t2x)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = np.where(np.abs(det) > 1e-12 * np.abs(scale) + 1e-300, 1.0 / det, np.nan)
    coef[:, 0] = (c00 * r0 + c01 * r1 + c02 * r2) * inv_det
    coef[:, 1] = (c01 * r0 + c11 * r1 + c12 * r2) * inv_det
    coef[:, 2] = (c02 * r0 + c12 * r1 + c22 * r2) * inv_det
    weight[:] = s0
    inflation[:] = s0 * (c00 * inv_det)
    if rows is None:
        return
    # the equivalent kernel's row sides [c, w] (first row rho of the inverse normal matrix, about the centroid;
    # zero where singular): c = rho_0 - rho_1 t1 . x - rho_2 t2 . x, w = rho_1 t1 + rho_2 t2
    inv0 = np.where(np.isfinite(inv_det), inv_det, 0.0)
    r0, r1, r2 = c00 * inv0, c01 * inv0, c02 * inv0
    rows[:, 0] = r0 - r1 * t1x - r2 * t2x
    for dim in range(3):
        rows[:, 1 + dim] = r1 * tangents[0][dim] + r2 * tangents[1][dim]


def _kernel_sums_numpy(indptr, indices, data, counts, rows, mark, removed, near, mixed, squared, nearby):
    # one signature for both paths: this one selects the columns ``rows``, the compiled loop looks cells up in ``mark``
    import scipy.sparse as sp  # imported where used (0.16 s): --help and verbs without it do not pay

    n = indptr.size - 1
    if rows.size:  # scipy's column selection walks the CSR indices once (no transposed copy); only the rows hit
        columns = sp.csr_matrix((data, indices, indptr), shape=(n, n))[:, rows]
        hit = np.flatnonzero(np.diff(columns.indptr))
        mixed[hit] -= columns[hit] @ removed
    start = 0
    while start < n:  # row blocks of about BLOCK_POINTS kernel entries (at least one row)
        stop = min(n, max(start + 1, int(np.searchsorted(indptr, indptr[start] + BLOCK_POINTS, "right")) - 1))
        first, last = indptr[start], indptr[stop]
        j, k, local = indices[first:last], data[first:last], indptr[start : stop + 1] - first
        squared[start:stop] = sp.csr_matrix((k * k, j, local), shape=(stop - start, n)) @ counts
        nearby[start:stop] = sp.csr_matrix(((k >= near).astype(np.float64), j, local), shape=(stop - start, n)) @ counts
        start = stop

def _equivalent_back_numpy(indptr, indices, data, rows, sums, x, out):
    # L^T x = sums . (K^T (rows x)): a sparse product with four columns (K^T a CSC view: no transposed copy)
    import scipy.sparse as sp  # imported where used (0.16 s): --help and verbs without it do not pay

    n = indptr.size - 1
    total = sp.csr_matrix((data, indices, indptr), shape=(n, n)).T @ (rows * x[:, None])
    out += sums[:, 0] * total[:, 0] + (sums[:, 1] * total[:, 1] + sums[:, 2] * total[:, 2] + sums[:, 3] * total[:, 3])


def _equivalent_forward_numpy(indptr, indices, data, rows, sums, x, out):
    # L x = rows . (K (sums x))
    import scipy.sparse as sp

    n = indptr.size - 1
    total = sp.csr_matrix((data, indices, indptr), shape=(n, n)) @ (sums * x[:, None])
    out[:] = rows[:, 0] * total[:, 0] + (rows[:, 1] * total[:, 1] + rows[:, 2] * total[:, 2] + rows[:, 3] * total[:, 3])


def _twiced_variance_numpy(indptr, indices, data, rows, sums, plain, twiced):
    import scipy.sparse as sp

    n = indptr.size - 1
    row = np.repeat(np.arange(n), np.diff(indptr))
    weights = sp.csr_matrix((data * np.einsum("zd,zd->z", rows[row], sums[indices, :4]), indices, indptr),
                            shape=(n, n))
    count = sums[:, 0]
    inverse = np.where(count > 0, 1.0 / np.where(count > 0, count, 1.0), 0.0)
    plain[:] = weights.multiply(weights) @ inverse
    both = 2.0 * weights - weights @ weights
    twiced[:] = both.multiply(both) @ inverse


# ------------------------------------------------------------------------------------------------ compiled path
def _locate_block_loop(points, start, stop, affine, hi, layout, table, cell_mm, nodes, max_d,
                       out_row, out_j, out_u, out_v, out_d, cells):  # fmt: skip
    count = 0
    for p in range(start, stop):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        g0 = x * affine[0, 0] + y * affine[0, 1] + z * affine[0, 2] + affine[0, 3]
        g1 = x * affine[1, 0] + y * affine[1, 1] + z * affine[1, 2] + affine[1, 3]
        g2 = x * affine[2, 0] + y * affine[2, 1] + z * affine[2, 2] + affine[2, 3]
        j = table[_flat(np.int64(_cell(g0, hi[0])), layout, 0) + _flat(np.int64(_cell(g1, hi[1])), layout, 1)
                  + _flat(np.int64(_cell(g2, hi[2])), layout, 2)]
        node = nodes[j]
        o0 = (g0 - node[0]) * cell_mm
        o1 = (g1 - node[1]) * cell_mm
        o2 = (g2 - node[2]) * cell_mm
        u = node[3] * o0 + node[4] * o1 + node[5] * o2
        v = node[6] * o0 + node[7] * o1 + node[8] * o2
        w = node[9] * o0 + node[10] * o1 + node[11] * o2
        d = w - (node[12] * u + node[13] * v + node[14] * u * u + node[15] * u * v + node[16] * v * v)
        if abs(d) <= max_d and u * u + v * v <= node[17]:
            out_row[count] = p
            out_j[count] = j
            out_u[count] = u
            out_v[count] = v
            out_d[count] = d
            if cells is not None:
                _add_one(cells, j, np.float64(out_u[count]), np.float64(out_v[count]), np.float64(out_d[count]), 1.0)
            count += 1
    return count


def _tile_order_loop(points, affine, hi, tile, counts, out):
    # a counting sort, stable like the numpy twin's argsort: count per tile, prefix sums, place
    counts[:] = 0
    for p in range(points.shape[0]):
        counts[_tile_key(points, p, affine, hi, tile) + 1] += 1
    for k in range(1, counts.size):
        counts[k] += counts[k - 1]
    for p in range(points.shape[0]):
        key = _tile_key(points, p, affine, hi, tile)
        r = counts[key]
        out[r, 0] = points[p, 0]
        out[r, 1] = points[p, 1]
        out[r, 2] = points[p, 2]
        counts[key] = r + 1


def _tile_key(points, p, affine, hi, tile):
    x, y, z = points[p, 0], points[p, 1], points[p, 2]
    key = np.int64(0)
    for k in range(3):
        g = x * affine[k, 0] + y * affine[k, 1] + z * affine[k, 2] + affine[k, 3]
        key = key * (np.int64(hi[k]) + 1) + np.int64(_cell(g / tile, hi[k]))
    return key


def _flat(cell, layout, k):
    # axis k's part of the table entry of a cell (its index ``cell`` along the axis): brick and place in the brick
    return (cell >> layout[k, 0]) * layout[k, 2] + (cell & layout[k, 1]) * layout[k, 3]


def _cell(g, hi):
    index = np.floor(g)
    if not index >= 0.0:  # NaN too, as np.fmax does
        index = 0.0
    if index > hi:
        index = hi
    return index


def _add_one(cells, j, u, v, d, sign):
    cells[j, 0] += sign
    cells[j, 1] += sign * u
    cells[j, 2] += sign * v
    cells[j, 3] += sign * (u * u)
    cells[j, 4] += sign * (u * v)
    cells[j, 5] += sign * (v * v)
    cells[j, 6] += sign * d
    cells[j, 7] += sign * (d * u)
    cells[j, 8] += sign * (d * v)


def _add_moments_loop(j, u32, v32, d32, sign, cells):
    for p in range(j.size):
        _add_one(cells, j[p], np.float64(u32[p]), np.float64(v32[p]), np.float64(d32[p]), sign)


def _plane_residuals_loop(j, u, v, d, coef, out):
    for p in range(j.size):
        i = j[p]
        out[p] = np.float64(d[p]) - (coef[i, 0] + coef[i, 1] * np.float64(u[p]) + coef[i, 2] * np.float64(v[p]))


def _outliers_loop(j, u, v, d, coef, limit, out_drop):
    count = 0
    inliers = 0
    squares = 0.0
    for p in range(j.size):
        i = j[p]
        # rounded to float32 as a stored residual (plane_residuals): the same points drop on both paths
        r = np.float64(np.float32(np.float64(d[p]) - (coef[i, 0] + coef[i, 1] * np.float64(u[p])
                                                      + coef[i, 2] * np.float64(v[p]))))
        if abs(r) > limit:
            out_drop[count] = p
            count += 1
        elif np.isfinite(r):
            inliers += 1
            squares += r * r
    return count, inliers, squares


def _raw_moments_loop(cells, basis, rows):
    out = np.empty((rows.size, 14))
    for r in range(rows.size):
        i = rows[r]
        out[r, 0] = cells[i, 0]
        for dim in range(3):
            out[r, 1 + dim] = cells[i, 0] * basis[i, 0, dim] + cells[i, 1] * basis[i, 1, dim] + cells[i, 2] * basis[
                i, 2, dim]
            out[r, 11 + dim] = cells[i, 6] * basis[i, 0, dim] + cells[i, 7] * basis[i, 1, dim] + cells[i, 8] * basis[
                i, 2, dim]
        second = _second_moments(cells[i, 0], cells[i, 1], cells[i, 2], cells[i, 3], cells[i, 4], cells[i, 5],
                                 basis[i, 0], basis[i, 1], basis[i, 2])  # fmt: skip
        for c in range(6):
            out[r, 4 + c] = second[c]
        out[r, 10] = cells[i, 6]
    return out


def _node_fits_loop(mixed, frames, t1x, t2x, coef, weight, inflation, rows):
    for i in range(mixed.shape[0]):
        s0, d0 = mixed[i, 0], mixed[i, 10]
        ts0 = frames[i, 0, 0] * mixed[i, 1] + frames[i, 0, 1] * mixed[i, 2] + frames[i, 0, 2] * mixed[i, 3]
        ts1 = frames[i, 1, 0] * mixed[i, 1] + frames[i, 1, 1] * mixed[i, 2] + frames[i, 1, 2] * mixed[i, 3]
        td0 = frames[i, 0, 0] * mixed[i, 11] + frames[i, 0, 1] * mixed[i, 12] + frames[i, 0, 2] * mixed[i, 13]
        td1 = frames[i, 1, 0] * mixed[i, 11] + frames[i, 1, 1] * mixed[i, 12] + frames[i, 1, 2] * mixed[i, 13]
        q0, q1, q2 = _tangent_forms(mixed[i, 4:10], frames[i, 0], frames[i, 1])
        c00, c01, c02, c11, c12, c22, det, scale, r0, r1, r2 = _plane_system(s0, ts0, ts1, q0, q1, q2, d0, td0, td1,
                                                                             t1x[i], t2x[i])  # fmt: skip
        inv_det = 1.0 / det if abs(det) > 1e-12 * abs(scale) + 1e-300 else np.nan
        coef[i, 0] = (c00 * r0 + c01 * r1 + c02 * r2) * inv_det
        coef[i, 1] = (c01 * r0 + c11 * r1 + c12 * r2) * inv_det
        coef[i, 2] = (c02 * r0 + c12 * r1 + c22 * r2) * inv_det
        weight[i] = s0
        inflation[i] = s0 * (c00 * inv_det)
        if rows is not None:
            inv0 = inv_det if np.isfinite(inv_det) else 0.0
            r0, r1, r2 = c00 * inv0, c01 * inv0, c02 * inv0
            rows[i, 0] = r0 - r1 * t1x[i] - r2 * t2x[i]
            for dim in range(3):
                rows[i, 1 + dim] = r1 * frames[i, 0, dim] + r2 * frames[i, 1, dim]


def _kernel_sums_loop(indptr, indices, data, counts, rows, mark, removed, near, mixed, squared, nearby):
    taken = np.empty(removed.shape[1])
    for i in range(indptr.size - 1):
        square = 0.0
        close = 0.0
        hits = 0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            k = data[e]
            c = counts[j]
            square += k * k * c
            if k >= near:
                close += c
            m = mark[j]
            if m >= 0:
                if hits == 0:
                    taken[:] = 0.0
                hits += 1
                for col in range(removed.shape[1]):
                    taken[col] += k * removed[m, col]
        squared[i] = square
        nearby[i] = close
        if hits:
            for col in range(removed.shape[1]):
                mixed[i, col] -= taken[col]


def _equivalent_back_loop(indptr, indices, data, rows, sums, x, out):
    # out += L^T x, L_ij = K_ij (c_i n_j + w_i . P_j) made as it is used
    for i in range(indptr.size - 1):
        xi = x[i]
        if xi == 0.0:
            continue
        r0, r1, r2, r3 = rows[i, 0] * xi, rows[i, 1] * xi, rows[i, 2] * xi, rows[i, 3] * xi
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            out[j] += data[e] * (r0 * sums[j, 0] + (r1 * sums[j, 1] + r2 * sums[j, 2] + r3 * sums[j, 3]))


def _equivalent_forward_loop(indptr, indices, data, rows, sums, x, out):
    # out = L x
    for i in range(indptr.size - 1):
        r0, r1, r2, r3 = rows[i, 0], rows[i, 1], rows[i, 2], rows[i, 3]
        total = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            total += data[e] * (r0 * sums[j, 0] + (r1 * sums[j, 1] + r2 * sums[j, 2] + r3 * sums[j, 3])) * x[j]
        out[i] = total


def _twiced_variance_loop(indptr, indices, data, rows, sums, plain, twiced):
    n = indptr.size - 1
    count = sums[:, 0]
    weights = np.empty(indices.size)
    for i in range(n):
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            weights[e] = data[e] * (rows[i, 0] * sums[j, 0] + rows[i, 1] * sums[j, 1] + rows[i, 2] * sums[j, 2]
                                    + rows[i, 3] * sums[j, 3])
    row = np.zeros(n)  # row i of 2 L - L L, dense, reset after each row
    seen = np.full(n, -1, np.int64)
    touched = np.empty(n, np.int64)
    for i in range(n):
        m = 0
        square = 0.0
        for e in range(indptr[i], indptr[i + 1]):
            j = indices[e]
            if count[j] > 0:
                square += weights[e] * weights[e] / count[j]
            if seen[j] != i:
                seen[j] = i
                touched[m] = j
                m += 1
            row[j] += 2.0 * weights[e]
        for e in range(indptr[i], indptr[i + 1]):
            k = indices[e]
            a = weights[e]
            for f in range(indptr[k], indptr[k + 1]):
                j = indices[f]
                if seen[j] != i:
                    seen[j] = i
                    touched[m] = j
                    m += 1
                row[j] -= a * weights[f]
        total = 0.0
        for q in range(m):
            j = touched[q]
            if count[j] > 0:
                total += row[j] * row[j] / count[j]
            row[j] = 0.0
        plain[i] = square
        twiced[i] = total


def _unsigned(fast: bool, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Index arrays (the kernel's, the grid's nodes, the points' nodes) as unsigned views for the compiled loops:
    numba checks every signed index for a negative one to wrap around (the loops over the kernel's entries ran 2-3
    times slower); unchanged for numpy."""
    if not fast or _MODE is False:
        return arrays
    return tuple(a.view(a.dtype.str.replace("i", "u")) for a in arrays)


def _kernel(name: str, fast: bool = True):
    """The compiled loop ``name`` when ``fast`` and the compiled path is not switched off (numba imported and the
    loops compiled, or loaded from numba's cache, on first use), else the numpy function of the same job."""
    if not fast or _MODE is False:
        return globals()[name.replace("_loop", "_numpy")]
    with _JIT_LOCK:  # the first scan's threads arrive here together
        if not _JIT:
            from numba import njit

            module = globals()
            # called from the loops: compiled inline into them
            for helper in ("_cell", "_flat", "_tile_key", "_add_one", "_second_moments", "_tangent_forms",
                           "_plane_system"):
                module[helper] = njit(nogil=True, cache=True, inline="always")(module[helper])
            for loop in ("_locate_block_loop", "_add_moments_loop", "_plane_residuals_loop", "_outliers_loop",
                         "_raw_moments_loop", "_node_fits_loop", "_kernel_sums_loop", "_equivalent_back_loop",
                         "_equivalent_forward_loop", "_twiced_variance_loop", "_tile_order_loop"):  # fmt: skip
                _JIT[loop] = njit(nogil=True, cache=True)(module[loop])
    return _JIT[name]


# ------------------------------------------------------------------------------------------------ the interface
def locate_block(points: np.ndarray, start: int, stop: int, affine: np.ndarray, hi: np.ndarray, layout: np.ndarray,
                 table: np.ndarray, cell_mm: float, nodes: np.ndarray, max_d: float,
                 out_row: np.ndarray, out_j: np.ndarray, out_u: np.ndarray, out_v: np.ndarray, out_d: np.ndarray,
                 cells: np.ndarray | None, fast: bool = True) -> int:  # fmt: skip
    """Locate points[start:stop] (M, 3) mm; returns how many passed the gates.

    affine: (3, 4) map of a point to grid units (rotation, registration and cell size folded in); hi (3,) the last
    cell index per axis; layout (3, 4) int64: where a cell's node is in ``table`` (:func:`grid_layout`); table: the
    grid's cells' nearest nodes (int32) in that order; nodes: (N, 18)
    per node [position in grid units (3), t1, t2, n (9), quadric c0..c4 (5), squared tangential gate (1)];
    max_d: largest |distance|, mm. The passing points' rows (int64), nodes (int32), u, v, d (float32, mm) go to the
    first ``count`` entries of the out buffers (each at least stop - start long); with ``cells`` (N, 9) float64
    their moments are added to it. ``fast``: the compiled path where it is not switched off (all functions here).
    """
    return int(_kernel("_locate_block_loop", fast)(points, start, stop, affine, hi, layout, *_unsigned(fast, table),
                                                   cell_mm, nodes, max_d, out_row, out_j, out_u, out_v, out_d,
                                                   cells))  # fmt: skip


def grid_layout(shape: np.ndarray, brick: np.ndarray) -> np.ndarray:
    """Where the lookup grid's cell (c0, c1, c2) is in its flat table: sum over the axes k of
    (c_k >> shift_k) * outer_k + (c_k & mask_k) * inner_k, returned as rows [shift, mask, outer, inner] (3, 4) int64.
    shape (3,): cells per axis, whole bricks; brick (3,): cells per axis of a brick, powers of two. The table holds
    the bricks in C order, each brick's cells in C order (:func:`brick_order`); brick (1, 1, 1) is the plain C
    order of the whole grid."""
    shape, brick = np.asarray(shape, np.int64), np.asarray(brick, np.int64)
    outer = shape // brick
    volume = int(np.prod(brick))
    layout = np.empty((3, 4), np.int64)
    layout[:, 0] = np.round(np.log2(brick)).astype(np.int64)
    layout[:, 1] = brick - 1
    layout[:, 2] = [outer[1] * outer[2] * volume, outer[2] * volume, volume]
    layout[:, 3] = [brick[1] * brick[2], brick[2], 1]
    return layout


def brick_order(plain: np.ndarray, brick: np.ndarray) -> np.ndarray:
    """The grid's table (S0, S1, S2) as the flat table of :func:`grid_layout` (each S_k a multiple of brick_k)."""
    (s0, s1, s2), (b0, b1, b2) = plain.shape, (int(b) for b in brick)
    bricks = plain.reshape(s0 // b0, b0, s1 // b1, b1, s2 // b2, b2).transpose(0, 2, 4, 1, 3, 5)
    return np.ascontiguousarray(bricks).ravel()


def tile_order(points: np.ndarray, affine: np.ndarray, grid_hi: np.ndarray, cell_mm: float,
               fast: bool = True) -> np.ndarray:
    """A copy of ``points`` (M, 3) mm sorted by tiles of ``TILE_CELLS`` grid cells when they are in no spatial order,
    else ``points`` itself. affine (3, 4): a point to grid units (as :func:`locate_block`); grid_hi (3,) the last
    cell index per axis; cell_mm the grid's cell. Stable (within a tile the points keep their order), the same order
    on both paths.

    Why: every step of a scan reads the grid and node rows of each point's cell; in a scanner's line order those are
    mostly in cache, in no order nearly every point misses (paper 1M: 2.7 times the time, 10M: 7.8 times; sorted by
    tiles, sort included, a shuffled cloud runs as fast as a scanned one: benchmarks/RESULTS.md, 2026-11-25). The copy
    costs 24 bytes a point, for such clouds only."""
    m = points.shape[0]
    if m < 2:
        return points
    at = np.linspace(0, m - 2, min(m - 1, 4096)).astype(np.int64)
    if not np.nanmedian(np.linalg.norm(points[at + 1] - points[at], axis=1)) > UNORDERED_STEP_CELLS * cell_mm:
        return points
    hi = np.floor(np.asarray(grid_hi, np.float64) / TILE_CELLS)
    counts = np.empty(int(np.prod(hi + 1)) + 1, np.int64)
    out = np.empty_like(points)
    _kernel("_tile_order_loop", fast)(points, affine, hi, float(TILE_CELLS), counts, out)
    return out


def add_moments(j: np.ndarray, u: np.ndarray, v: np.ndarray, d: np.ndarray, sign: float, cells: np.ndarray,
                fast: bool = True) -> None:
    """cells (N, 9) += sign * per-node sums of [1, u, v, uu, uv, vv, d, du, dv] of the points (K,) at nodes j."""
    _kernel("_add_moments_loop", fast)(*_unsigned(fast, j), u, v, d, float(sign), cells)


def plane_residuals(j: np.ndarray, u: np.ndarray, v: np.ndarray, d: np.ndarray, coef: np.ndarray,
                    fast: bool = True) -> np.ndarray:
    """Residuals (K,) float32 mm of the points (nodes j, u, v, d (K,)) from their own node's plane coef (N, 3)."""
    out = np.empty(j.size, np.float32)
    _kernel("_plane_residuals_loop", fast)(*_unsigned(fast, j), u, v, d, coef, out)
    return out


def outliers(j: np.ndarray, u: np.ndarray, v: np.ndarray, d: np.ndarray, coef: np.ndarray, limit: float,
             fast: bool = True) -> tuple[np.ndarray, int, float]:
    """The second pass's split of the points (nodes j, u, v, d (K,)) by their residual (float32, as
    :func:`plane_residuals`) from their own node's plane coef (N, 3): the points (indices, int64) whose |residual|
    exceeds ``limit`` mm, and the count and sum of squares (mm^2) of the other finite residuals. No array of K
    residuals is formed (blocks on the numpy path, one loop compiled)."""
    drop = np.empty(j.size, np.int64)  # only the pages written become resident: a few outliers
    count, inliers, squares = _kernel("_outliers_loop", fast)(*_unsigned(fast, j), u, v, d, coef, float(limit), drop)
    return drop[:count].copy(), int(inliers), float(squares)


def raw_moments(cells: np.ndarray, basis: np.ndarray, rows: np.ndarray, fast: bool = True) -> np.ndarray:
    """Raw 3D moments (K, 14) of the cells ``rows`` (K,) from their sums (N, 9) and the node basis (N, 3, 3) (rows
    x about the centroid, t1, t2); see ScanFieldEstimator."""
    return _kernel("_raw_moments_loop", fast)(cells, basis, rows)


def node_fits(mixed: np.ndarray, frames: np.ndarray, t1x: np.ndarray, t2x: np.ndarray, fast: bool = True,
              equivalent: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Per node the weighted plane fit from mixed raw moments (N, 14): coefficients (N, 3) [a mm, b_u, b_v], weight
    (N,), intercept variance inflation (N,) and the fit's equivalent kernel as rows (N, 4) [c_i, w_i]: the intercept
    is rho_i . [sum d, sum d u, sum d v] over the kernel-weighted points, rho_i the first row of the inverse normal
    matrix, and cell j's points sum to [n_j, t1_i . (P_j - n_j x_i), t2_i . (P_j - n_j x_i)] in node i's frame (P_j
    their position sum about the centroid), so it takes c_i n_j + w_i . P_j of them with c_i = rho_i0 - rho_i1
    t1_i . x_i - rho_i2 t2_i . x_i and w_i = rho_i1 t1_i + rho_i2 t2_i (zero where singular; None unless
    ``equivalent``). The 3x3 normal equations solved in closed form (adjugate), NaN where singular."""
    n = mixed.shape[0]
    coef, weight, inflation, rows = np.empty((n, 3)), np.empty(n), np.empty(n), np.empty((n, 4)) if equivalent else None
    loop = _kernel("_node_fits_loop", fast)
    edges = np.linspace(0, n, max(1, min(_workers(fast), n // NODE_BLOCK)) + 1).astype(np.int64)

    def part(k: int) -> None:  # nodes edges[k]:edges[k + 1], on a thread of their own
        s = slice(int(edges[k]), int(edges[k + 1]))
        loop(mixed[s], frames[s], t1x[s], t2x[s], coef[s], weight[s], inflation[s], None if rows is None else rows[s])

    on_threads(part, edges.size - 1)
    return coef, weight, inflation, rows


def kernel_sums(kernel_indptr: np.ndarray, kernel_indices: np.ndarray, kernel_data: np.ndarray, counts: np.ndarray,
                rows: np.ndarray, removed: np.ndarray, near: float, mixed: np.ndarray,
                fast: bool = True) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The second pass's node sums of the (N, N) CSR kernel K (indptr (N + 1,), indices, data), in one pass over it
    (no transposed, squared or thresholded copy of K: in a fresh process building those cost more than a scan):

    mixed (N, 14) -= K[:, rows] @ removed: the raw moments ``removed`` (R, 14) of the cells ``rows`` (R,), unique,
    taken back out (K is not symmetric: per-node radii); returns sum_j K_ij^2 counts_j (N,) and sum_j counts_j over
    the K_ij >= ``near`` (N,), with counts (N,) the cells' point counts. Per row, the terms are summed in the kernel's
    entry order on both paths (the same numbers bit for bit; the numpy path in scipy's sparse products, by blocks of
    rows).
    """
    n = kernel_indptr.size - 1
    mark = np.full(n, -1, np.int32)  # the compiled loop's: row of ``removed`` per cell, -1 for none
    mark[rows] = np.arange(rows.size)
    squared, nearby = np.empty(n), np.empty(n)
    counts = np.ascontiguousarray(counts, dtype=np.float64)  # once: a column of the cell sums would be copied per block
    removed = np.ascontiguousarray(removed, dtype=np.float64)
    loop = _kernel("_kernel_sums_loop", fast)
    indptr, indices = _unsigned(fast, kernel_indptr, kernel_indices)
    # the compiled loop takes a run of rows as its indptr's slice (entry offsets stay absolute); the numpy path whole
    parts = row_parts(kernel_indptr, _workers(fast))

    def part(k: int) -> None:
        a, b = parts[k]
        loop(indptr[a : b + 1], indices, kernel_data, counts, rows, mark, removed, float(near), mixed[a:b],
             squared[a:b], nearby[a:b])

    on_threads(part, len(parts))
    return squared, nearby


def covariance_sums(kernel_indptr: np.ndarray, kernel_indices: np.ndarray, kernel_data: np.ndarray, rows: np.ndarray,
                    raw: np.ndarray, t: np.ndarray, twiced: bool, fast: bool = True) -> np.ndarray:
    """t (A D A^T t) (N,), elementwise, for t (N,), D = diag(1 / n) (zero where n is 0) and A the node values'
    weights on the cells' mean distances (with t = 1 / s the correlation sums of ScanFieldEstimator._error_model):
    the plane fit's equivalent weights L_ij = K_ij (c_i n_j + w_i . P_j) on the pattern of the (N, N) CSR kernel K
    (indptr, indices, data), or A = 2 L - L L with ``twiced``.

    rows (N, 4): [c_i, w_i] (:func:`node_fits`); the cells' counts n_j and position sums P_j about the skin centroid:
    the first four columns of their raw moments (N, 14) (:func:`raw_moments`). Compiled: two passes over K (plain)
    or four (twiced), L's entries made as they are used; numpy: sparse products with four columns, L never formed.
    The same numbers to rounding."""
    n = kernel_indptr.size - 1
    indptr, indices = _unsigned(fast, kernel_indptr, kernel_indices)
    back_rows, forward_rows = _kernel("_equivalent_back_loop", fast), _kernel("_equivalent_forward_loop", fast)
    t = np.ascontiguousarray(t, dtype=np.float64)
    # n_j and P_j side by side (the raw moments' rows are 112 bytes: 16.6 -> 13.3 ms a call at paper resolution); on
    # one thread: two, each over half the rows, took 16-21 ms (both bound by the same random reads of these sums)
    sums = np.ascontiguousarray(raw[:, :4], dtype=np.float64)

    def back(x: np.ndarray) -> np.ndarray:  # L^T x
        out = np.zeros(n)
        back_rows(indptr, indices, kernel_data, rows, sums, x, out)
        return out

    def forward(x: np.ndarray) -> np.ndarray:  # L x
        out = np.empty(n)
        forward_rows(indptr, indices, kernel_data, rows, sums, x, out)
        return out

    y = back(t)
    if twiced:
        y = 2.0 * y - back(y)
    count = sums[:, 0]
    y = np.where(count > 0, y / np.where(count > 0, count, 1.0), 0.0)
    f = forward(y)
    return t * (2.0 * f - forward(f) if twiced else f)


def threads() -> int:
    """Threads the scan step runs its parallel parts on: one per core, up to 4."""
    return min(os.cpu_count() or 1, 4)


def _workers(fast: bool) -> int:
    """Threads for a compiled loop over the kernel's rows or the nodes (:func:`threads`: its loops release the GIL);
    one on the numpy path (which works by blocks of its own)."""
    return threads() if fast and _MODE is not False else 1


def row_parts(indptr: np.ndarray, parts: int) -> list[tuple[int, int]]:
    """Up to ``parts`` ranges of consecutive rows of a CSR matrix with about equal entries, at least
    BLOCK_POINTS entries each (a thread is not worth less)."""
    parts = max(1, min(parts, int(indptr[-1]) // BLOCK_POINTS))
    edges = np.unique(np.searchsorted(indptr, np.linspace(0, indptr[-1], parts + 1)).clip(0, indptr.size - 1))
    edges[0], edges[-1] = 0, indptr.size - 1
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges)]


def on_threads(job, count: int) -> None:
    """job(0) .. job(count - 1), on as many threads (the compiled loops release the GIL, scipy's products too)."""
    if count == 1:
        job(0)
        return
    with ThreadPoolExecutor(count) as pool:
        list(pool.map(job, range(count)))


def twiced_variance(kernel_indptr: np.ndarray, kernel_indices: np.ndarray, kernel_data: np.ndarray, rows: np.ndarray,
                    raw: np.ndarray,
                    fast: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The diagonals (N,) of L D L^T and of (2 L - L L) D (2 L - L L)^T, D = diag(1 / n) (zero where n is 0), for the
    equivalent weights L of :func:`covariance_sums` (same arguments): the plain and the twiced fit's node
    variance per unit point noise. The twiced one needs L L, two rings wide: row by row into a dense scratch row
    (compiled) or scipy's sparse product (numpy)."""
    n = kernel_indptr.size - 1
    plain, twiced = np.empty(n), np.empty(n)
    _kernel("_twiced_variance_loop", fast)(*_unsigned(fast, kernel_indptr, kernel_indices), kernel_data, rows,
                                           np.ascontiguousarray(raw[:, :4]), plain, twiced)
    return plain, twiced
