"""Multi-view fusion (core/scan/fusion.py) against truths it does not make: the synthetic scanner's true poses and
hit points, Monte Carlo draws of independent view errors, and hand-made rigid transforms."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hood_decomp.core.scan.fusion import ScanView, check_pose, fuse_fields, fuse_views, pose_difference
from hood_decomp.core.scan.registration import rotation_from_vector
from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator
from hood_decomp.core.types import DisplacementField, FieldErrorModel, SkinSurface
from hood_decomp.errors import ScanError
from hood_decomp.synthetic.scanner import random_rigid
from tests.multiview import scanned_part


@pytest.fixture(scope="module")
def part(coarse_hood):
    """One part (LOCK_L 0.4, BUFFER_R -0.3 mm) in three partial views; view 2's robot pose 2 mm / 0.2 deg off."""
    skin = coarse_hood.skin
    member, scans = scanned_part(coarse_hood, {"LOCK_L": 0.4, "BUFFER_R": -0.3}, 100, marker_noise_mm=0.02,
                                 n_holes=1, pose_error_deg=0.0, pose_error_mm=0.0)
    rng = np.random.default_rng(0)
    views = []
    for k, scan in enumerate(scans):
        pose = scan.true_transform @ random_rigid(rng, *((0.2, 2.0) if k == 1 else (0.002, 0.02)))
        views.append(ScanView(scan.points, pose, scan.markers, scan.markers_nominal, name=f"view {k + 1}",
                              pose_source="robot"))
    return skin, member, scans, views, fuse_views(skin, views, estimator=prepared_estimator(skin))


def test_fused_coverage_is_the_union_of_the_views_and_of_their_merged_points(part):
    """Fails if a node seen by some view is lost or a node no view saw gets a value (fused coverage differs from the
    union of the views' own fields, each made here by field_from_scan at the scanner's TRUE pose, a path that does not
    fuse), if the views are not partial (each below 80 % of the skin, the union above every view), or if the fused
    coverage is more than 1 % off the coverage of one field made from all views' points merged in the part frame."""
    skin, _, scans, _, fused = part
    est = prepared_estimator(skin)
    own = [field_from_scan(skin, s.points, scanner_pose=s.true_transform, estimator=est, min_coverage=0.02)[0]
           for s in scans]
    seen = np.array([np.isfinite(f.normal_displacement) for f in own])
    union = seen.any(axis=0)
    assert all(f.coverage < 0.8 for f in own) and union.mean() > max(f.coverage for f in own) + 0.1
    fused_seen = np.isfinite(fused.field.normal_displacement)
    assert np.array_equal(fused_seen, union), int(np.sum(fused_seen != union))
    merged = est.field(np.vstack([s.points @ s.true_transform[:3, :3].T + s.true_transform[:3, 3] for s in scans]))
    assert abs(merged.coverage - fused.field.coverage) <= 0.01, (merged.coverage, fused.field.coverage)


def test_a_view_whose_robot_pose_is_off_is_corrected_by_its_markers(part):
    """Fails if the view whose robot pose is 2 mm / 0.2 deg off keeps an error beyond 3.5 stated stds (any twist
    component of its registration against the scanner's true pose, in the marker fit's stated pose covariance) or its
    Mahalanobis distance d2 beyond the 99.9 % point of its law (the marker noise is estimated from the fit's residual
    with 3K - 6 dof: d2 / 6 ~ F(6, 3K - 6)), or if the reported correction is not the 2 mm moved."""
    from scipy.stats import f

    _, _, scans, views, fused = part
    result = fused.views[1]
    registration = result.registration
    assert registration.method.startswith("markers")
    delta = registration.transform @ np.linalg.inv(scans[1].true_transform)
    angle = np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1))
    skew = (delta[:3, :3] - delta[:3, :3].T) / 2
    omega = np.array([skew[2, 1], skew[0, 2], skew[1, 0]]) * (angle / np.sin(angle) if angle > 1e-12 else 1.0)
    center = registration.pose_center
    twist = np.concatenate([omega, delta[:3, :3] @ center + delta[:3, 3] - center])
    std = np.sqrt(np.diag(registration.pose_covariance))
    assert np.all(np.abs(twist / std) <= 3.5), twist / std
    dof = 3 * registration.n_markers - 6
    assert twist @ np.linalg.solve(registration.pose_covariance, twist) <= 6 * f.ppf(0.999, 6, dof)
    robot_shift, _ = pose_difference(views[1].scanner_pose, scans[1].true_transform)
    assert robot_shift > 1.0 and abs(result.pose_correction_mm - robot_shift) < 0.2 * robot_shift


def test_fused_error_model_predicts_the_scatter_of_independent_view_errors():
    """Monte Carlo, independent of the fusion formulas: two overlapping views of a 1D strip of nodes with white node
    noise (0.02 and 0.04 mm) and each its own pose error (a rigid twist drawn from its covariance, applied through the
    rigid-body motion of the nodes). Fails if the fused node std or the fused registration modes' variance differ from
    the scatter of 2,000 draws by more than 12 % (3.8 sampling stds), if the pose errors of different views are
    treated as one (the correlation between a node seen only by view 1 and one seen only by view 2 must be about 0),
    or if the fused value is not weighted by each view's whole node variance, noise and pose (its scatter would exceed
    the better view's where the other view's pose error reaches far)."""
    rng = np.random.default_rng(3)
    n = 60
    points = np.column_stack([np.linspace(0.0, 1000.0, n), np.zeros(n), np.zeros(n)])
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    skin = SkinSurface(points, normals, np.zeros((0, 3), np.int64), "m")
    seen1, seen2 = np.arange(n) < 40, np.arange(n) >= 20
    cov1 = np.diag([1e-8, 1e-8, 1e-8, 1e-4, 1e-4, 1e-4])
    cov2 = np.diag([4e-8, 4e-8, 4e-8, 4e-4, 4e-4, 4e-4])
    center1, center2 = np.array([200.0, 0, 0]), np.array([800.0, 0, 0])

    def view(values, seen, std, cov, center):
        errors = FieldErrorModel("scan", np.where(seen, std, np.nan), np.ones(n), 0.0, cov, center)
        return DisplacementField("m", np.where(seen, values, np.nan), float(seen.mean()), std, errors)

    def rigid(cov, center):
        z = rng.multivariate_normal(np.zeros(6), cov)
        return (np.cross(z[:3], points - center) + z[3:]) @ normals[0]

    draws = []
    for _ in range(2000):
        a = rng.normal(0, 0.02, n) + rigid(cov1, center1)
        b = rng.normal(0, 0.04, n) + rigid(cov2, center2)
        draws.append(fuse_fields([view(a, seen1, 0.02, cov1, center1),
                                  view(b, seen2, 0.04, cov2, center2)], skin).normal_displacement)
    draws = np.array(draws)
    fused = fuse_fields([view(np.zeros(n), seen1, 0.02, cov1, center1), view(np.zeros(n), seen2, 0.04, cov2, center2)],
                        skin)
    modes = fused.errors.registration_modes(points, normals)
    predicted = fused.errors.node_std**2 + np.sum(modes**2, axis=1)
    empirical = draws.var(axis=0)
    assert np.all(np.abs(empirical / predicted - 1) < 0.12), np.max(np.abs(empirical / predicted - 1))
    # overlap nodes: better than the better view alone
    alone = view(np.zeros(n), seen1, 0.02, cov1, center1).errors
    assert np.all(empirical[20:40] < 0.02**2 + np.sum(alone.registration_modes(points, normals)[20:40] ** 2, axis=1))
    c = np.corrcoef(draws[:, 5], draws[:, 55])[0, 1]
    assert abs(c) < 0.09, c  # 4 sampling stds of a zero correlation over 2,000 draws
    predicted_cov = modes[5] @ modes[55]
    assert abs(predicted_cov) < 1e-12
    assert np.all(np.isfinite(fused.errors.node_std)) and fused.coverage == 1.0
    # the single-pose summary never states less node variance than the exact per-view model
    summary = dataclasses.replace(fused.errors, view_poses=())
    assert np.all(np.sum(summary.registration_modes(points, normals) ** 2, axis=1)
                  >= np.sum(modes**2, axis=1) * (1 - 1e-9))


def test_the_fused_bias_statement_is_the_views_largest():
    """Fails if fusing views loses either part of the smoothing-bias statement or takes the smaller one: the fused
    field states the largest bias correlation and the largest bias variance floor of its views (the views' skins
    may have been prepared apart; the larger is the conservative statement)."""
    n = 10
    points = np.column_stack([np.linspace(0.0, 900.0, n), np.zeros(n), np.zeros(n)])
    skin = SkinSurface(points, np.tile([0.0, 0.0, 1.0], (n, 1)), np.zeros((0, 3), np.int64), "m")
    views = [DisplacementField("m", np.zeros(n), 1.0, 0.02, FieldErrorModel(
        "scan", np.full(n, 0.002), np.ones(n), 0.0, bias_correlation=correlation, bias_variance_floor=floor))
        for correlation, floor in ((40.0, 3e-6), (25.0, 7e-6))]
    fused = fuse_fields(views, skin).errors
    assert fused.bias_correlation == 40.0 and fused.bias_variance_floor == 7e-6


def test_a_multi_view_part_refuses_a_view_without_a_pose_by_name(part):
    """Fails if a multi-view part accepts a view without a scanner pose (even one with markers), or does not name it;
    or if a lone view without a pose is refused (it is in the part frame, registered by its markers)."""
    skin, _, _, views, _ = part
    no_pose = dataclasses.replace(views[2], scanner_pose=None, name="view from the left")
    with pytest.raises(ScanError, match="view from the left: no scanner pose"):
        fuse_views(skin, [views[0], views[1], no_pose])
    lone = fuse_views(skin, [dataclasses.replace(no_pose)], min_coverage=0.02)
    assert lone.views[0].registration.method.startswith("markers")


@pytest.mark.parametrize(("pose", "fragment"), [
    (np.eye(3), "4 x 4"),
    (np.full((4, 4), np.nan), "non-finite"),
    (np.diag([1.001, 1.0, 1.0, 1.0]), "not orthonormal"),
    (np.diag([-1.0, 1.0, 1.0, 1.0]), "mirrors"),
    (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
    ("abc", "16 numbers"),
])
def test_check_pose_names_what_is_wrong(pose, fragment):
    """Fails if a non-rigid, mis-shaped or non-finite pose passes, or the error does not name the problem."""
    with pytest.raises(ScanError, match=fragment):
        check_pose(pose, "pose of view 3")
    rigid = np.eye(4)
    rigid[:3, :3] = rotation_from_vector(np.array([0.1, -0.2, 0.3]))
    rigid[:3, 3] = [1.0, 2.0, 3.0]
    assert np.array_equal(check_pose(np.round(rigid, 7).ravel().tolist()), np.round(rigid, 7))
