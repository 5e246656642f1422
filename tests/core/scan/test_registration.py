"""Registration: markers recover the scanner pose, datum regions remove a part misplacement without swallowing the
deformation, a whole-surface best fit would swallow it, bad registration input is refused."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.core.scan.registration import (
    MarkerNoiseHistory,
    check_marker_noise,
    marker_pose_covariance,
    register_scan,
    rigid_from_markers,
    rotation_from_vector,
)
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan
from hood_decomp.errors import ScanError
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan
from tests.skins import along_normals, crowned_patch, datum_mask, smooth_field


@pytest.fixture(scope="module")
def skin():
    return crowned_patch(57, 49)


@pytest.fixture(scope="module")
def truth(skin):
    return smooth_field(skin, amplitude_mm=1.0)


@pytest.fixture(scope="module")
def estimator(skin):
    return ScanFieldEstimator().fit(skin)


def _scan(skin, truth, seed=0, **config):
    cfg = ScannerConfig(**{"n_points": 100_000, "noise_mm": 0.05, **config})
    return synthesize_scan(skin, along_normals(skin, truth), cfg, seed)


def _rms(field, truth):
    return float(np.sqrt(np.nanmean((field.normal_displacement - truth) ** 2)))


def test_kabsch_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    nominal = rng.uniform(-800, 800, (6, 3))
    rotation = rotation_from_vector(np.array([0.3, -0.2, 0.9]))
    translation = np.array([120.0, -40.0, 2500.0])
    measured = (nominal - translation) @ rotation  # measured = R^T (nominal - t)
    transform, rms = rigid_from_markers(measured, nominal)
    np.testing.assert_allclose(transform[:3, :3], rotation, atol=1e-12)
    np.testing.assert_allclose(transform[:3, 3], translation, atol=1e-9)
    assert rms < 1e-9


def test_kabsch_refuses_too_few_or_collinear_markers():
    with pytest.raises(ScanError, match="at least 3"):
        rigid_from_markers(np.zeros((2, 3)), np.zeros((2, 3)))
    line = np.outer(np.arange(4.0), [1.0, 2.0, 3.0])
    with pytest.raises(ScanError, match="collinear"):
        rigid_from_markers(line, line)
    with pytest.raises(ScanError, match="matching"):
        rigid_from_markers(np.zeros((4, 3)), np.zeros((5, 3)))


def test_markers_recover_the_scanner_pose(skin, truth, estimator):
    scan = _scan(skin, truth, seed=1, pose_error_deg=1.0, pose_error_mm=20.0)
    result = register_scan(scan.points, estimator, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal)
    assert result.method == "markers" and result.n_markers == len(scan.markers) >= 6
    # Compare where it matters: the registered positions of the skin nodes.
    probe = skin.points
    back = (probe - scan.true_transform[:3, 3]) @ scan.true_transform[:3, :3]  # part -> scanner frame (truth)
    mapped = back @ result.transform[:3, :3].T + result.transform[:3, 3]
    assert np.max(np.linalg.norm(mapped - probe, axis=1)) < 0.02
    assert result.marker_rms_mm < 0.02
    assert result.overlap > 0.7


def test_nominal_pose_alone_registers_an_exact_cell(skin, truth, estimator):
    scan = _scan(skin, truth, seed=2, pose_error_deg=0.0, pose_error_mm=0.0)
    field, result = field_from_scan(skin, scan.points, scanner_pose=scan.scanner_pose, estimator=estimator)
    assert result.method == "pose"
    assert _rms(field, truth) < 0.008


def test_datum_alignment_removes_a_part_misplacement(skin, truth, estimator):
    """The part seated 0.25 mm off along the surface normal at the fixed hinge: what the datum corner observes.

    One patch cannot tell a shift along its normal from one with an in-plane part (it sees in-plane shifts only
    through its slight curvature), so the misplacement here is along the datum's mean normal.
    """
    datum = datum_mask(skin)
    normal = skin.normals[datum].mean(axis=0)
    shift = 0.25 * normal / np.linalg.norm(normal)
    scan = _scan(skin, truth, seed=3, misplacement=(0.0, 0.0, 0.0, *shift))
    markers = {"markers_mm": scan.markers, "markers_nominal_mm": scan.markers_nominal, "estimator": estimator}
    plain, _ = field_from_scan(skin, scan.points, **markers)
    aligned, result = field_from_scan(skin, scan.points, datum_mask=datum, **markers)
    print(f"plain {_rms(plain, truth):.4f} aligned {_rms(aligned, truth):.4f}")
    assert result.method == "markers+datum" and result.converged
    assert result.n_datum_points > 500
    assert _rms(plain, truth) > 0.2  # the misplacement is there without the datum step ...
    assert _rms(aligned, truth) < 0.01  # ... and gone with it
    # What one corner determines: its normal shift; its tilts and in-plane shifts would spray noise over the far field.
    assert 1 <= result.n_aligned <= 3
    assert result.alignment_std_mm <= 0.005


def test_datum_alignment_keeps_the_deformation_a_whole_surface_fit_swallows(skin, truth, estimator):
    scan = _scan(skin, truth, seed=4)
    common = {"markers_mm": scan.markers, "markers_nominal_mm": scan.markers_nominal, "estimator": estimator}
    datum, _ = field_from_scan(skin, scan.points, datum_mask=datum_mask(skin), **common)
    whole, _ = field_from_scan(skin, scan.points, datum_mask=np.ones(skin.n_nodes, bool), **common)
    assert _rms(datum, truth) < 0.01
    assert _rms(whole, truth) > 0.1


def test_bad_registration_input_is_refused(skin, truth, estimator):
    scan = _scan(skin, truth, seed=5)
    with pytest.raises(ScanError, match="one entry per skin node"):
        register_scan(scan.points, estimator, datum_mask=np.ones(10, bool))
    with pytest.raises(ScanError, match="do not fit"):
        register_scan(scan.points, estimator, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal[::-1])
    with pytest.raises(ScanError, match=r"\(4, 4\)"):
        register_scan(scan.points, estimator, scanner_pose=np.eye(3))


def test_a_stated_marker_noise_is_checked_against_the_marker_residual(skin, truth, estimator):
    """Fails if a stated marker noise reaches the field's pose covariance unchecked (stated 3 times too small, or 5
    times too large, it must be rejected by name on every scan and replaced by the residual's estimate), if a right
    statement is rejected more often than the 0.1 % rate allows (at most 1 of 16), or if the statistic is not
    chi-square with 3K - 6 dof (its mean over the right statements must be within 3.3 standard errors of the dof).
    Truth: the synthetic scanner's marker-centre noise, 0.03 mm per coordinate, 8 markers."""
    true_mm, chi2, wrongly_rejected = 0.03, [], 0
    for seed in range(16):
        scan = _scan(skin, truth, seed=200 + seed, n_points=10_000, marker_noise_mm=true_mm)
        for stated in (true_mm, true_mm / 3, true_mm * 5):
            field, registration = field_from_scan(skin, scan.points, markers_mm=scan.markers,
                                                  markers_nominal_mm=scan.markers_nominal, estimator=estimator,
                                                  min_coverage=0.0, marker_std_mm=stated)
            check = registration.marker_noise
            assert check.dof == 3 * len(scan.markers) - 6 == 18
            used = stated if check.accepted else check.estimated_mm
            np.testing.assert_allclose(field.errors.pose_covariance,
                                       marker_pose_covariance(scan.markers_nominal, used)[0], rtol=1e-12)
            if stated == true_mm:
                chi2.append(check.chi2)
                wrongly_rejected += not check.accepted
            else:
                word = "too small" if stated < true_mm else "too large"
                assert not check.accepted and word in check.reason and check.used_mm == check.estimated_mm, check
    assert wrongly_rejected <= 1
    assert abs(np.mean(chi2) - 18.0) < 3.3 * np.sqrt(2 * 18 / len(chi2)), np.mean(chi2)


def test_a_scanners_recent_clouds_reject_an_understatement_one_cloud_lets_through(skin, truth):
    """Fails if the scan node's history does not pool the clouds' marker residuals: stated 1.5 times too small
    (0.02 against the synthetic scanner's 0.03 mm), one cloud's check alone lets it through in at least a third of
    30 clouds (it rejects with P = 0.35 each; measured 16 of 30), the pooled check (20 clouds) rejects it in at
    least 27 of them (from the 5th cloud on with P >= 0.95 each; measured 30); a right statement is rejected at
    most once in 30; a new statement starts a new pool; without a statement or markers nothing is checked."""
    history, right, own_rejected, pooled_rejected, right_rejected = MarkerNoiseHistory(), MarkerNoiseHistory(), 0, 0, 0
    for seed in range(30):
        scan = _scan(skin, truth, seed=300 + seed, n_points=2_000, marker_noise_mm=0.03)
        used, check = history.statement(0.02, scan.markers, scan.markers_nominal)
        assert check.clouds == min(seed + 1, 20) and check.dof == 18 * check.clouds
        assert used == (0.02 if check.accepted else None)
        pooled_rejected += not check.accepted
        own_rejected += not check_marker_noise(np.sqrt(check.estimated_mm**2 * 18 / 8), 8, 0.02).accepted
        right_rejected += not right.statement(0.03, scan.markers, scan.markers_nominal)[1].accepted
    assert own_rejected <= 20 and pooled_rejected >= 27 and right_rejected <= 1, (own_rejected, pooled_rejected)
    assert history.statement(0.05, scan.markers, scan.markers_nominal)[1].clouds == 1
    assert history.statement(None, scan.markers, scan.markers_nominal) == (None, None)
    assert history.statement(0.05, None, None) == (0.05, None)


def test_the_marker_noise_check_refuses_what_it_cannot_judge():
    """Fails if a check without enough markers or of a non-positive stated noise gives a verdict instead of a
    named error."""
    with pytest.raises(ScanError, match="at least 3 markers"):
        check_marker_noise(0.01, 2, 0.01)
    for bad in (0.0, -0.01, float("nan")):
        with pytest.raises(ScanError, match="finite number > 0"):
            check_marker_noise(0.01, 8, bad)
