"""A synthetic structured-light scanner for tests and demos (paper section 4.3.1-4.3.2).

It scans the *displaced* visible skin as a single-shot structured-light system would: a camera casts one ray per
pixel, a projector beside it must light the same point (projector shadows drop points), steep incidence drops
points, and what it sees is the skin in a fixture: a frame of bars around and below the part (background points
beyond the free edges), a clamp above one edge (an occluded region) and reference markers on the frame whose centres
the scanner reports separately, as structured-light software does. On top: Gaussian range noise along the ray,
random dropouts and dropout holes (highlights), outliers along the ray, an error of the scanner pose against its
nominal calibration (the markers recover it) and optionally a rigid misplacement of the part in the fixture.

Ray casting uses open3d's RaycastingScene (float32); hit points are rebuilt in float64 from the hit triangle and its
barycentric coordinates and moved onto a smooth (Phong) interpolation of the displaced mesh through the displaced
nodes and their normals, so the scanned part is smooth like a real one and not faceted like the FE mesh.

Frames: the part frame is the model's; the fixture frame coincides with it for a nominally placed part. Output points
are in the scanner (camera) frame, x_part = R x_scan + t with (R, t) = ``true_transform``. Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hood_decomp.core.scan.registration import rotation_from_vector
from hood_decomp.core.types import SkinSurface
from hood_decomp.errors import ScanError


@dataclass(frozen=True)
class ScannerConfig:
    """Scanner set-up and its imperfections (mm, degrees).

    n_points: target number of points on the skin (the paper's single shot gives about 1 million).
    noise_mm: standard deviation of the range noise along the ray.
    standoff_mm: camera distance from the skin centroid along the mean skin normal; baseline_mm: projector offset.
    outlier_fraction: share of points moved along their ray by 0.5-20 mm either way.
    dropout_fraction: share of single points lost at random; n_holes, hole_radius_mm: lost round patches.
    max_incidence_deg: steepest angle between ray and surface normal that still returns a point.
    fixture: build the fixture (frame bars, clamp, markers) into the scene.
    marker_noise_mm: noise of each reported marker centre (per coordinate).
    pose_error_deg, pose_error_mm: size of the random error of the scanner pose against its nominal calibration.
    misplacement: rigid misplacement of the part in the fixture, (rx, ry, rz) rotation vector in degrees then
        (tx, ty, tz) translation in mm, about the skin centroid in part axes.
    smooth: scan the Phong-smoothed displaced skin instead of its flat facets.
    view_center: where a partial view aims, as fractions (-1..1) of the skin's half extents along its two principal
        axes ((0, 0): the centroid, the whole-part view).
    view_tilt_deg: the view direction tilted from the mean skin normal about the skin's first and second principal
        axes (a robot looking at the part from the side).
    fov_deg: full angle of a square field of view (a partial view); None: the whole skin plus 8 %.
    """

    n_points: int = 1_000_000
    noise_mm: float = 0.02
    standoff_mm: float = 2500.0
    baseline_mm: float = 400.0
    outlier_fraction: float = 0.002
    dropout_fraction: float = 0.01
    n_holes: int = 3
    hole_radius_mm: float = 40.0
    max_incidence_deg: float = 75.0
    fixture: bool = True
    marker_noise_mm: float = 0.005
    pose_error_deg: float = 0.5
    pose_error_mm: float = 5.0
    misplacement: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    smooth: bool = True
    view_center: tuple[float, float] = (0.0, 0.0)
    view_tilt_deg: tuple[float, float] = (0.0, 0.0)
    fov_deg: float | None = None


@dataclass(frozen=True)
class SyntheticScan:
    """One synthetic scan and its truth.

    points: (M, 3) float64, mm, scanner frame (skin, fixture background and outliers: raw scanner output).
    scanner_pose: (4, 4) the *nominal* scanner-to-part transform, as the cell's calibration knows it.
    markers: (K, 3) mm, measured marker centres, scanner frame; marker_ids: (K,) int64.
    markers_nominal: (K, 3) mm, nominal marker centres in the part (fixture) frame, same rows.
    true_transform: (4, 4) the exact scanner-to-part transform (registration should find it).
    misplacement: (4, 4) the part's rigid misplacement in the fixture (x_fixture = M x_part).
    noise_mm: range noise used; n_skin_points: points that landed on the skin; n_outliers: points made outliers.
    """

    points: np.ndarray
    scanner_pose: np.ndarray
    markers: np.ndarray
    marker_ids: np.ndarray
    markers_nominal: np.ndarray
    true_transform: np.ndarray
    misplacement: np.ndarray
    noise_mm: float
    n_skin_points: int
    n_outliers: int


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(N, 3) unit area-weighted vertex normals of a triangle mesh (right-hand winding)."""
    corner = points[triangles]
    face = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    normals = np.zeros_like(points)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def random_rigid(rng: np.random.Generator, angle_deg: float, shift_mm: float) -> np.ndarray:
    """A (4, 4) rigid transform with a random axis, rotation angle_deg and translation of length shift_mm (a pose
    error: ``pose @ random_rigid(...)`` turns and shifts the pose about its own origin)."""
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    transform = np.eye(4)
    transform[:3, :3] = rotation_from_vector(np.radians(angle_deg) * axis / np.linalg.norm(axis))
    transform[:3, 3] = shift_mm * direction / np.linalg.norm(direction)
    return transform


def _misplacement(values: tuple[float, ...], center: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform: rotation vector values[:3] (deg) about ``center``, then translation values[3:] (mm)."""
    rotation = rotation_from_vector(np.radians(np.asarray(values[:3], dtype=np.float64)))
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = center - rotation @ center + np.asarray(values[3:], dtype=np.float64)
    return transform


def _box(center: np.ndarray, half: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and outward-wound triangles (12, 3) of a box with the given centre, half sizes and axes."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    vertices = center + (signs * half) @ axes
    faces = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    return vertices, faces


def _part_frame(skin: SkinSurface) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid (3,), axes (3, 3) rows e1, e2, n (n the mean outward normal) and half extents (3,) of the skin."""
    center = skin.points.mean(axis=0)
    normal = skin.normals.mean(axis=0)
    normal /= np.linalg.norm(normal)
    flat = (skin.points - center) - np.outer((skin.points - center) @ normal, normal)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    e1 = vt[0] - (vt[0] @ normal) * normal
    e1 /= np.linalg.norm(e1)
    axes = np.array([e1, np.cross(normal, e1), normal])
    local = (skin.points - center) @ axes.T
    return center, axes, np.abs(local).max(axis=0)


def _fixture(skin: SkinSurface) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """Fixture geometry in the fixture frame: boxes (vertices, triangles) and marker centres (K, 3).

    Four frame bars 60 mm outside the skin's outline and 40 mm below its lowest point, a clamp 60 mm above the skin
    near one long edge, and two markers on top of each bar.
    """
    center, axes, half = _part_frame(skin)
    low = -half[2] - 60.0
    boxes, markers = [], []
    for along, across in ((0, 1), (1, 0)):
        for side in (-1.0, 1.0):
            bar_center = np.zeros(3)
            bar_center[across] = side * (half[across] + 90.0)
            bar_center[2] = low
            bar_half = np.array([0.0, 0.0, 20.0])
            bar_half[along] = half[along] + 120.0
            bar_half[across] = 25.0
            boxes.append(_box(center + bar_center @ axes, bar_half, axes))
            for frac in (-0.6, 0.6):
                marker = bar_center.copy()
                marker[along] = frac * half[along]
                marker[2] = low + 20.0
                markers.append(center + marker @ axes)
    clamp_center = np.array([0.3 * half[0], -half[1] + 40.0, 0.0])
    clamp_center[2] = half[2] + 60.0
    boxes.append(_box(center + clamp_center @ axes, np.array([60.0, 40.0, 20.0]), axes))
    return boxes, np.array(markers)


def _phong(
    hit: np.ndarray, bary: np.ndarray, corners: np.ndarray, normals: np.ndarray
) -> np.ndarray:
    """Phong tessellation with shape factor 1/2: the flat hit (M, 3) moved half way to sum_k b_k * (its projection
    onto the tangent plane of corner k). With 1/2 a parabola through the corners is reproduced exactly along the edges
    (the usual 3/4 overshoots the sagitta by half, 1 by a factor of two).

    bary: (M, 3) barycentric weights; corners, normals: (M, 3, 3) corner positions and unit normals.
    """
    offset = np.einsum("mkd,mkd->mk", hit[:, None, :] - corners, normals)
    return hit - 0.5 * np.einsum("mk,mk,mkd->md", bary, offset, normals)


def synthesize_scan(
    skin: SkinSurface,
    displacement_mm: np.ndarray,
    config: ScannerConfig | None = None,
    seed: int = 0,
) -> SyntheticScan:
    """Scan the skin displaced by ``displacement_mm`` (N, 3), mm; see the module docstring and ScannerConfig."""
    import open3d as o3d  # heavy import, only the synthetic scanner needs it

    cfg = config if config is not None else ScannerConfig()
    displacement = np.asarray(displacement_mm, dtype=np.float64)
    if displacement.shape != skin.points.shape:
        raise ScanError(f"displacement must be (N, 3) = {skin.points.shape} mm; got {displacement.shape}")
    rng = np.random.default_rng(seed)
    misplacement = _misplacement(cfg.misplacement, skin.points.mean(axis=0))
    displaced = skin.points + displacement
    # Normals of the displaced skin: the model's normals turned by the change the displacement makes to the mesh.
    nominal_normals = vertex_normals(skin.points, skin.triangles)
    winding = np.sign(np.einsum("nd,nd->n", nominal_normals, skin.normals))[:, None]  # the mesh may wind either way
    turned = skin.normals + winding * (vertex_normals(displaced, skin.triangles) - nominal_normals)
    turned /= np.linalg.norm(turned, axis=1, keepdims=True)
    world = displaced @ misplacement[:3, :3].T + misplacement[:3, 3]
    world_normals = turned @ misplacement[:3, :3].T

    center, axes, half = _part_frame(skin)
    # Nominal scanner pose: camera above the aim point (the centroid for a whole-part view) looking down the mean
    # normal, tilted for a partial view; x_part = R x_cam + position.
    aim = center + cfg.view_center[0] * half[0] * axes[0] + cfg.view_center[1] * half[1] * axes[1]
    tilt = rotation_from_vector(np.radians(cfg.view_tilt_deg[0]) * axes[0] + np.radians(cfg.view_tilt_deg[1]) * axes[1])
    view_axes = axes @ tilt.T  # rows e1, e2, n turned by the tilt
    cam_rotation = np.column_stack([view_axes[0], -view_axes[1], -view_axes[2]])
    nominal_pose = np.eye(4)
    nominal_pose[:3, :3] = cam_rotation
    nominal_pose[:3, 3] = aim + cfg.standoff_mm * view_axes[2]
    actual_pose = nominal_pose @ random_rigid(rng, cfg.pose_error_deg, cfg.pose_error_mm)

    scene = o3d.t.geometry.RaycastingScene()
    skin_id = scene.add_triangles(world.astype(np.float32), skin.triangles.astype(np.uint32))
    markers_nominal = np.zeros((0, 3))
    if cfg.fixture:
        boxes, markers_nominal = _fixture(skin)
        for vertices, faces in boxes:
            scene.add_triangles(vertices.astype(np.float32), faces.astype(np.uint32))

    origin = actual_pose[:3, 3]
    rotation = actual_pose[:3, :3]
    # Field of view: the skin's angular extent plus 8 % (the fixture around it shows up as background).
    if cfg.fov_deg is None:
        corners_local = (world - origin) @ rotation
        tan = corners_local[:, :2] / corners_local[:, 2:3]
        lo, hi = tan.min(axis=0), tan.max(axis=0)
        lo, hi = lo - 0.08 * (hi - lo), hi + 0.08 * (hi - lo)
    else:
        # a partial view: a square field of view about the (actual) optical axis
        lo, hi = np.full(2, -np.tan(np.radians(cfg.fov_deg) / 2)), np.full(2, np.tan(np.radians(cfg.fov_deg) / 2))

    def cast(nu: int, nv: int) -> tuple[np.ndarray, dict]:
        gu, gv = np.meshgrid(np.linspace(lo[0], hi[0], nu), np.linspace(lo[1], hi[1], nv), indexing="ij")
        local = np.column_stack([gu.ravel(), gv.ravel(), np.ones(gu.size)])
        directions = local @ rotation.T
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        rays = np.hstack([np.broadcast_to(origin, directions.shape), directions]).astype(np.float32)
        return directions, scene.cast_rays(o3d.core.Tensor(rays))

    _, probe = cast(200, 200)
    skin_share = float(np.mean(probe["geometry_ids"].numpy() == skin_id))
    if skin_share == 0.0:
        raise ScanError("the scanner does not see the skin from its pose")
    keep_share = (1.0 - cfg.dropout_fraction) * 0.9  # rough allowance for shadows, holes and steep incidence
    n_rays = cfg.n_points / (skin_share * keep_share)
    aspect = (hi[0] - lo[0]) / (hi[1] - lo[1])
    nu, nv = int(np.sqrt(n_rays * aspect)), int(np.sqrt(n_rays / aspect))
    directions, result = cast(nu, nv)
    geometry = result["geometry_ids"].numpy().astype(np.int64)
    hit = geometry != o3d.t.geometry.RaycastingScene.INVALID_ID
    directions, geometry = directions[hit], geometry[hit]
    primitive = result["primitive_ids"].numpy()[hit].astype(np.int64)
    uv = result["primitive_uvs"].numpy()[hit].astype(np.float64)
    face_normal = result["primitive_normals"].numpy()[hit].astype(np.float64)
    t_hit = result["t_hit"].numpy()[hit].astype(np.float64)

    on_skin = geometry == skin_id
    points = origin + directions * t_hit[:, None]
    # Skin hits rebuilt in float64 on the hit triangle, then onto the smooth surface.
    tri = skin.triangles[primitive[on_skin]]
    bary = np.column_stack([1.0 - uv[on_skin, 0] - uv[on_skin, 1], uv[on_skin, 0], uv[on_skin, 1]])
    flat = np.einsum("mk,mkd->md", bary, world[tri])
    points[on_skin] = _phong(flat, bary, world[tri], world_normals[tri]) if cfg.smooth else flat

    cos_incidence = np.abs(np.einsum("md,md->m", directions, face_normal))
    keep = cos_incidence >= np.cos(np.radians(cfg.max_incidence_deg))
    # Projector shadow: the projector must reach the same point first.
    projector = origin + cfg.baseline_mm * rotation[:, 0]
    to_point = points - projector
    distance = np.linalg.norm(to_point, axis=1)
    proj_dirs = to_point / distance[:, None]
    proj_rays = np.hstack([np.broadcast_to(projector, proj_dirs.shape), proj_dirs]).astype(np.float32)
    proj_t = scene.cast_rays(o3d.core.Tensor(proj_rays))["t_hit"].numpy().astype(np.float64)
    keep &= proj_t >= distance - 0.5
    keep &= rng.random(points.shape[0]) >= cfg.dropout_fraction
    if cfg.n_holes > 0:
        centres = world[rng.choice(world.shape[0], cfg.n_holes, replace=False)]
        for hole in centres:
            keep &= ~(on_skin & (np.linalg.norm(points - hole, axis=1) < cfg.hole_radius_mm))
    points, directions, on_skin = points[keep], directions[keep], on_skin[keep]

    points += directions * rng.normal(0.0, cfg.noise_mm, points.shape[0])[:, None]
    n_outliers = round(cfg.outlier_fraction * points.shape[0])
    chosen = rng.choice(points.shape[0], n_outliers, replace=False)
    jump = rng.uniform(0.5, 20.0, n_outliers) * rng.choice([-1.0, 1.0], n_outliers)
    points[chosen] += directions[chosen] * jump[:, None]

    to_scanner = np.linalg.inv(actual_pose)
    points_scan = points @ to_scanner[:3, :3].T + to_scanner[:3, 3]
    markers, marker_ids, nominal = _visible_markers(scene, markers_nominal, origin, to_scanner, cfg, rng)
    return SyntheticScan(
        points=points_scan,
        scanner_pose=nominal_pose,
        markers=markers,
        marker_ids=marker_ids,
        markers_nominal=nominal,
        true_transform=np.linalg.inv(misplacement) @ actual_pose,
        misplacement=misplacement,
        noise_mm=float(cfg.noise_mm),
        n_skin_points=int(on_skin.sum()),
        n_outliers=n_outliers,
    )


def _visible_markers(
    scene, markers: np.ndarray, origin: np.ndarray, to_scanner: np.ndarray, cfg: ScannerConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Markers the camera sees (nothing in front of them): measured centres (scanner frame), ids, nominal centres."""
    import open3d as o3d

    if markers.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    to_marker = markers - origin
    distance = np.linalg.norm(to_marker, axis=1)
    rays = np.hstack([np.broadcast_to(origin, markers.shape), to_marker / distance[:, None]]).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    visible = np.flatnonzero(t_hit >= distance - 1.0)
    measured = markers[visible] @ to_scanner[:3, :3].T + to_scanner[:3, 3]
    measured += rng.normal(0.0, cfg.marker_noise_mm, measured.shape)
    return measured, visible.astype(np.int64), markers[visible]
