"""Scan -> signed normal displacement field: accuracy against synthetic truth, sign, masks, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan
from hood_decomp.core.types import SkinSurface
from hood_decomp.errors import ScanError
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan
from tests.skins import RX_MM, RY_MM, along_normals, crown_height, crowned_patch, near_edge, smooth_field

N_POINTS = 100_000


@pytest.fixture(scope="module")
def skin() -> SkinSurface:
    return crowned_patch(57, 49, hole_radius_mm=110.0)


@pytest.fixture(scope="module")
def truth(skin: SkinSurface) -> np.ndarray:
    return smooth_field(skin, amplitude_mm=1.0)


@pytest.fixture(scope="module")
def estimator(skin: SkinSurface) -> ScanFieldEstimator:
    return ScanFieldEstimator().fit(skin)


def _scan(skin: SkinSurface, truth: np.ndarray, noise: float, seed: int = 3, **config: float):
    cfg = ScannerConfig(n_points=N_POINTS, noise_mm=noise, **config)
    return synthesize_scan(skin, along_normals(skin, truth), cfg, seed)


def _errors(skin: SkinSurface, field: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    err = field - truth
    seen = np.isfinite(err)
    edge = near_edge(skin, 30.0)  # the free-edge row of nodes (outer edges and the hole), spacing 25 mm
    return {
        "all": float(np.sqrt(np.mean(err[seen] ** 2))),
        "edge": float(np.sqrt(np.mean(err[seen & edge] ** 2))),
        "interior": float(np.sqrt(np.mean(err[seen & ~edge] ** 2))),
        "n_edge": int((seen & edge).sum()),
    }


@pytest.mark.parametrize(("noise", "limit_all", "limit_edge"), [(0.02, 0.004, 0.005), (0.05, 0.006, 0.008)])
def test_field_matches_truth_including_free_edges(skin, truth, estimator, noise, limit_all, limit_edge):
    scan = _scan(skin, truth, noise)
    field, registration = field_from_scan(
        skin, scan.points, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal, estimator=estimator
    )
    errors = _errors(skin, field.normal_displacement, truth)
    print(f"noise {noise}: {errors}, coverage {field.coverage:.3f}, noise_rms {field.noise_rms:.4f}")
    assert registration.method == "markers"
    assert errors["n_edge"] > 100
    assert errors["all"] < limit_all
    assert errors["edge"] < limit_edge
    assert errors["interior"] < limit_all
    assert field.coverage > 0.85
    assert field.model_id == skin.model_id
    # The noise estimate is the normal component of the range noise: sigma * cos(incidence), incidence < 25 deg here.
    assert 0.85 * noise < field.noise_rms < 1.1 * noise


def test_sign_comes_from_the_node_normal(skin, truth):
    """The same scan against the same skin with flipped normals gives exactly the negated field (open surface)."""
    scan = _scan(skin, truth, 0.02, fixture=False, pose_error_deg=0.0, pose_error_mm=0.0)
    points = scan.points @ scan.true_transform[:3, :3].T + scan.true_transform[:3, 3]
    flipped = SkinSurface(skin.points, -skin.normals, skin.triangles[:, ::-1], skin.model_id + "-flipped")
    up = ScanFieldEstimator().fit(skin).field(points).normal_displacement
    down = ScanFieldEstimator().fit(flipped).field(points).normal_displacement
    both = np.isfinite(up) & np.isfinite(down)
    assert both.mean() > 0.85
    np.testing.assert_allclose(down[both], -up[both], atol=1e-9)
    assert np.corrcoef(up[both], truth[both])[0, 1] > 0.999


def test_point_distances_against_analytic_offsets(estimator):
    """Points placed at known signed offsets along the analytic crown normal come back with those offsets."""
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-680, 680, 20000), rng.uniform(-580, 580, 20000)
    keep = np.hypot(x - 200.0, y - 150.0) > 140.0  # away from the hole
    x, y = x[keep], y[keep]
    normal = np.column_stack([x / RX_MM, y / RY_MM, np.ones_like(x)])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.uniform(-3.0, 3.0, x.size)
    points = np.column_stack([x, y, crown_height(x, y)]) + offset[:, None] * normal
    located = estimator.point_distances(points)
    assert np.all(located.node >= 0)
    np.testing.assert_allclose(located.distance, offset, atol=2e-3)
    gradient = estimator.distance_gradient(located)
    assert np.max(np.linalg.norm(gradient - normal, axis=1)) < 2e-3
    # Beyond the gates: far off the surface, 3.6 spacings past the outline on the surface's continuation, inside the
    # hole -> off the skin.
    off = np.array([[0.0, 0.0, 8.0], [790.0, 0.0, crown_height(790.0, 0.0)], [200.0, 150.0, crown_height(200, 150)]])
    assert np.all(estimator.point_distances(off).node == -1)


def test_unseen_nodes_are_nan_and_seen_nodes_are_not(skin, truth, estimator):
    scan = _scan(skin, truth, 0.02, seed=5, hole_radius_mm=110.0)
    points = scan.points @ scan.true_transform[:3, :3].T + scan.true_transform[:3, 3]
    field = estimator.field(points)
    on_skin = points[estimator.point_distances(points).node >= 0]
    gap, _ = cKDTree(on_skin).query(skin.points)
    value = field.normal_displacement
    # In a gap of the scan (clamp shadow, dropout holes), farther than half the radius plus one mesh spacing from any
    # scan point: no value, even with data all around. Densely surrounded: a value.
    unseen = gap > estimator.radius_mm_ / 2 + estimator.spacing_mm_
    assert unseen.sum() > 5 and np.isnan(value[unseen]).all()
    assert np.isfinite(value[gap < 3.0]).mean() > 0.98
    assert field.coverage == pytest.approx(np.isfinite(value).mean())


def test_outliers_do_not_bias_the_field(skin, truth, estimator):
    scan = _scan(skin, truth, 0.05, seed=11, outlier_fraction=0.03)
    field, _ = field_from_scan(
        skin, scan.points, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal, estimator=estimator
    )
    assert _errors(skin, field.normal_displacement, truth)["all"] < 0.01


@pytest.fixture(scope="module")
def clean_scan(skin, truth):
    return _scan(skin, truth, 0.02, seed=2)


def test_empty_scan_is_refused(skin):
    with pytest.raises(ScanError, match="empty"):
        field_from_scan(skin, np.zeros((0, 3)))


def test_all_nan_scan_is_refused(skin):
    with pytest.raises(ScanError, match="no finite points"):
        field_from_scan(skin, np.full((1000, 3), np.nan))


def test_wrong_shape_is_refused(skin):
    with pytest.raises(ScanError, match=r"\(M, 3\)"):
        field_from_scan(skin, np.zeros((10, 2)))


def test_scan_in_metres_is_detected(skin, clean_scan, estimator):
    with pytest.raises(ScanError, match="metres"):
        field_from_scan(skin, clean_scan.points / 1000.0, estimator=estimator)
    with pytest.raises(ScanError, match="scale does not match"):  # micrometres
        field_from_scan(skin, clean_scan.points * 1000.0, estimator=estimator)


def test_scan_that_does_not_overlap_is_refused(skin, clean_scan, estimator):
    far = clean_scan.points + np.array([0.0, 0.0, 400.0])  # right size, but 400 mm off along the view
    with pytest.raises(ScanError, match="does not overlap"):
        field_from_scan(
            skin, far, markers_mm=clean_scan.markers, markers_nominal_mm=clean_scan.markers_nominal, estimator=estimator
        )


def test_low_coverage_is_refused(skin, clean_scan, estimator):
    points = clean_scan.points @ clean_scan.true_transform[:3, :3].T + clean_scan.true_transform[:3, 3]
    corner = points[(points[:, 0] > 250.0) & (points[:, 1] > 200.0)]  # about a tenth of the part
    field, _ = field_from_scan(skin, corner, estimator=estimator, min_coverage=0.05)
    assert 0.05 < field.coverage < 0.2
    with pytest.raises(ScanError, match="coverage"):
        field_from_scan(skin, corner, estimator=estimator, min_coverage=0.5)


def test_unfitted_estimator_is_refused():
    with pytest.raises(ScanError, match="not fitted"):
        ScanFieldEstimator().field(np.zeros((5, 3)))


def test_parallel_location_of_a_large_scan_equals_one_chunk(estimator):
    """Above 400k points the location runs in threads; it must give exactly what one chunk gives."""
    rng = np.random.default_rng(8)
    x, y = rng.uniform(-720, 720, 450_000), rng.uniform(-620, 620, 450_000)
    points = np.column_stack([x, y, crown_height(x, y) + rng.normal(0.0, 2.0, x.size)])
    points[::1000] = np.nan  # NaN rows travel through both paths the same way
    whole = estimator._locate_chunk(points)
    parts = estimator._locate(points)
    for a, b in zip(whole, parts, strict=True):
        np.testing.assert_array_equal(a, b)
    assert whole[0].size > 300_000
