"""Synthetic visible skins and displacement fields with known truth, shared by the scan tests and the benchmark.

The skin is a doubly curved crowned open patch like a hood's outer skin: z = -x^2 / (2 Rx) - y^2 / (2 Ry) over
[-L/2, L/2] x [-W/2, W/2] mm, structured quads split into triangles, analytic outward normals (+z side), free edges
all round and optionally a round hole (an inner free edge). Fields are displacements along the node normals, so the
true signed normal displacement of a node is exactly the field value (no tangential part to second-guess).
"""

from __future__ import annotations

import numpy as np

from hood_decomp.core.types import SkinSurface, fingerprint

RX_MM = 4000.0
RY_MM = 3000.0


def crown_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height z (mm) of the crowned surface at (x, y) (mm)."""
    return -(x**2) / (2 * RX_MM) - y**2 / (2 * RY_MM)


def crowned_patch(
    nx: int = 57, ny: int = 49, length_mm: float = 1400.0, width_mm: float = 1200.0, hole_radius_mm: float = 0.0
) -> SkinSurface:
    """A crowned open patch of nx x ny nodes (quads split in two), optionally with a round hole at (200, 150) mm.

    Returns a SkinSurface with (N, 3) points, analytic unit normals pointing up (+z side) and triangles wound so that
    their right-hand normal agrees with the node normals.
    """
    xs = np.linspace(-length_mm / 2, length_mm / 2, nx)
    ys = np.linspace(-width_mm / 2, width_mm / 2, ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    points = np.column_stack([gx.ravel(), gy.ravel(), crown_height(gx, gy).ravel()])
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    triangles = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    if hole_radius_mm > 0:
        keep = np.hypot(points[:, 0] - 200.0, points[:, 1] - 150.0) >= hole_radius_mm
        triangles = triangles[keep[triangles].all(axis=1)]
        used = np.zeros(len(points), bool)
        used[triangles] = True
        new_index = np.cumsum(used) - 1
        points, triangles = points[used], new_index[triangles]
    normals = np.column_stack([points[:, 0] / RX_MM, points[:, 1] / RY_MM, np.ones(len(points))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    triangles = triangles.astype(np.int64)
    return SkinSurface(points, normals, triangles, fingerprint(points, triangles, "crowned-patch"))


def boundary_nodes(skin: SkinSurface) -> np.ndarray:
    """(N,) bool: nodes on a free edge (an edge used by exactly one triangle)."""
    tri = skin.triangles
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    mask = np.zeros(skin.n_nodes, bool)
    mask[unique[counts == 1].ravel()] = True
    return mask


def near_edge(skin: SkinSurface, distance_mm: float) -> np.ndarray:
    """(N,) bool: nodes within ``distance_mm`` of a free-edge node."""
    from scipy.spatial import cKDTree

    edge = boundary_nodes(skin)
    dist, _ = cKDTree(skin.points[edge]).query(skin.points)
    return dist <= distance_mm


def smooth_field(skin: SkinSurface, amplitude_mm: float = 1.0) -> np.ndarray:
    """(N,) mm: a boundary-effect-like normal displacement: cubic twist and sag plus a broad bump (sigma 250 mm).

    Value, slope and curvature vanish at the datum corner (-700, -600) mm (the 'fixed hinge'); within the datum
    region (150 mm) the field stays below 2e-3 * amplitude, so registration on that corner must not remove any of it.
    """
    x = (skin.points[:, 0] + 700.0) / 1400.0
    y = (skin.points[:, 1] + 600.0) / 1200.0
    bump = np.exp(-((skin.points[:, 0] - 250.0) ** 2 + (skin.points[:, 1] - 100.0) ** 2) / (2 * 250.0**2))
    return amplitude_mm * (0.8 * x * x * y + 0.6 * x * y * y - 0.5 * x**3 + 0.4 * y**3 + 0.5 * bump)


def datum_mask(skin: SkinSurface, radius_mm: float = 150.0) -> np.ndarray:
    """(N,) bool: skin nodes of the datum region near the fixed corner (-700, -600) mm."""
    return np.hypot(skin.points[:, 0] + 700.0, skin.points[:, 1] + 600.0) <= radius_mm


def along_normals(skin: SkinSurface, normal_displacement: np.ndarray) -> np.ndarray:
    """(N, 3) mm displacement of each node along its normal."""
    return skin.normals * normal_displacement[:, None]


# ---------------------------------------------------------------------------------------------------------------
# CloudCompare cross-check helpers, shared by tests/test_cloudcompare.py and benchmarks/bench_scan.py.

CLOUDCOMPARE = "CloudCompare"


def cloudcompare_c2m(cloud_ply: str, mesh_ply: str, out_ply: str) -> tuple[np.ndarray, float, float]:
    """Run CloudCompare's cloud-to-mesh distance headless (the paper's metric, section 3).

    Returns the signed distances (M,) of the cloud's points to the mesh (sign from the face normal), the wall time of
    the CloudCompare process (s, loading and saving included) and the time CloudCompare itself reports for the
    distance computation (s; NaN if its log does not say).
    """
    import os
    import re
    import subprocess
    import time

    from hood_decomp.io.ply import read_ply

    command = [CLOUDCOMPARE, "-SILENT", "-AUTO_SAVE", "OFF", "-C_EXPORT_FMT", "PLY", "-O", cloud_ply, "-O", mesh_ply,
               "-C2M_DIST", "-SAVE_CLOUDS", "FILE", out_ply]  # fmt: skip
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, timeout=900,
                          env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})  # fmt: skip
    wall = time.perf_counter() - start
    if done.returncode != 0 or not os.path.exists(out_ply):
        raise RuntimeError(f"CloudCompare failed ({done.returncode}): {done.stdout[-2000:]} {done.stderr[-2000:]}")
    reported = [float(t) for t in re.findall(r"\[ComputeDistances\] Time: ([0-9.]+) s", done.stdout)]
    fields = read_ply(out_ply).vertex_fields
    name = next(k for k in fields if "C2M" in k)
    return fields[name], wall, (sum(reported) if reported else float("nan"))


def mesh_scan_2p5d(points: np.ndarray, max_edge_mm: float) -> np.ndarray:
    """Triangles (T, 3) of a 2.5D Delaunay mesh of scan points over their x-y plane (the test skins face +z), wound
    so the face normals point +z, with triangles having an edge longer than ``max_edge_mm`` removed (gaps stay gaps).

    CloudCompare's own -DELAUNAY needs CGAL, which Debian's build lacks, so the scan is meshed here.
    """
    from scipy.spatial import Delaunay

    tri = Delaunay(points[:, :2]).simplices.astype(np.int64)
    p = points[tri]
    longest = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
    tri = tri[longest <= max_edge_mm]
    p = points[tri]
    up = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2] > 0
    return np.where(up[:, None], tri, tri[:, ::-1])
