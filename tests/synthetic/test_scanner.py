"""The synthetic structured-light scanner and the PLY scan files, against analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hood_decomp.errors import ScanError
from hood_decomp.io.ply import read_ply, read_scan, write_ply, write_scan
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan
from tests.skins import RX_MM, RY_MM, along_normals, crown_height, crowned_patch

QUIET = {"dropout_fraction": 0.0, "n_holes": 0, "outlier_fraction": 0.0, "fixture": False}


@pytest.fixture(scope="module")
def skin():
    return crowned_patch(41, 35)


def _part_frame(scan) -> np.ndarray:
    return scan.points @ scan.true_transform[:3, :3].T + scan.true_transform[:3, 3]


def _height_error(points: np.ndarray, offset_mm: float = 0.0) -> np.ndarray:
    """Signed distance (mm, along the analytic normal, first order) from the crown lifted by offset_mm."""
    x, y = points[:, 0], points[:, 1]
    cos = 1.0 / np.sqrt(1.0 + (x / RX_MM) ** 2 + (y / RY_MM) ** 2)
    return (points[:, 2] - crown_height(x, y)) * cos - offset_mm


def test_noise_free_scan_lies_on_the_smooth_displaced_surface(skin):
    """Phong-smoothed hits reproduce the analytic crown (lifted 0.3 mm along the normals) to micrometres."""
    scan = synthesize_scan(skin, along_normals(skin, np.full(skin.n_nodes, 0.3)),
                           ScannerConfig(n_points=40_000, noise_mm=0.0, **QUIET), seed=0)  # fmt: skip
    error = _height_error(_part_frame(scan), 0.3)
    assert 35_000 < scan.points.shape[0] < 50_000
    assert np.max(np.abs(error)) < 2e-3
    flat = synthesize_scan(skin, np.zeros_like(skin.points),
                           ScannerConfig(n_points=40_000, noise_mm=0.0, smooth=False, **QUIET), seed=0)  # fmt: skip
    # Flat facets sag below a convex crown by up to (edge^2 / 8R): tens of micrometres at 35 mm spacing.
    assert np.mean(_height_error(_part_frame(flat))) < -0.01


def test_range_noise_is_gaussian_along_the_ray(skin):
    noise = 0.05
    scan = synthesize_scan(skin, np.zeros_like(skin.points), ScannerConfig(n_points=40_000, noise_mm=noise, **QUIET))
    points = _part_frame(scan)
    error = _height_error(points)
    # Along the ray: the normal component is noise * cos(angle between ray and normal), 0.9 .. 1 here.
    ray = points - scan.true_transform[:3, 3]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    normal = np.column_stack([points[:, 0] / RX_MM, points[:, 1] / RY_MM, np.ones(len(points))])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    expected = noise * np.sqrt(np.mean(np.einsum("md,md->m", ray, normal) ** 2))
    assert np.std(error) == pytest.approx(expected, rel=0.03)
    assert abs(np.mean(error)) < 3 * noise / np.sqrt(len(error))


def test_fixture_markers_outliers_and_occlusion(skin):
    cfg = ScannerConfig(n_points=60_000, noise_mm=0.02, outlier_fraction=0.01, n_holes=2, hole_radius_mm=60.0)
    scan = synthesize_scan(skin, np.zeros_like(skin.points), cfg, seed=4)
    points = _part_frame(scan)
    # Markers: what the scanner reports maps onto the nominal centres through the true transform.
    assert len(scan.markers) >= 6
    mapped = scan.markers @ scan.true_transform[:3, :3].T + scan.true_transform[:3, 3]
    assert np.max(np.abs(mapped - scan.markers_nominal)) < 0.03
    # Background: the fixture frame shows up beyond the free edges, far below the skin.
    below = points[:, 2] < crown_height(points[:, 0], points[:, 1]) - 30.0
    assert below.sum() > 100
    # Outliers: about the requested share of the points is off the surface by 0.5 mm or more.
    on_part = (np.abs(points[:, 0]) < 700) & (np.abs(points[:, 1]) < 600) & ~below
    off = np.abs(_height_error(points[on_part]))
    on_part[on_part] = off < 25.0  # not the clamp, 100 mm above the skin
    off = off[off < 25.0]
    assert np.mean(off > 0.4) == pytest.approx(0.01, abs=0.003)
    # Occlusion: the clamp and the dropout holes leave skin regions without points.
    gap, _ = cKDTree(points[on_part]).query(skin.points)
    assert (gap > 40.0).sum() > 3
    assert scan.n_outliers == pytest.approx(0.01 * len(points), abs=2)


def test_scanner_pose_error_is_in_the_points_not_in_the_nominal_pose(skin):
    cfg = ScannerConfig(n_points=20_000, **QUIET, pose_error_deg=1.0, pose_error_mm=10.0)
    scan = synthesize_scan(skin, np.zeros_like(skin.points), cfg, seed=9)
    gap = scan.true_transform[:3, 3] - scan.scanner_pose[:3, 3]
    assert 5.0 < np.linalg.norm(gap) < 100.0  # 10 mm at the scanner plus 1 degree over the stand-off
    nominal = scan.points @ scan.scanner_pose[:3, :3].T + scan.scanner_pose[:3, 3]
    assert np.median(np.abs(_height_error(nominal))) > 1.0


def test_same_seed_same_scan_and_bad_displacement(skin):
    cfg = ScannerConfig(n_points=10_000)
    a = synthesize_scan(skin, np.zeros_like(skin.points), cfg, seed=5)
    b = synthesize_scan(skin, np.zeros_like(skin.points), cfg, seed=5)
    np.testing.assert_array_equal(a.points, b.points)
    with pytest.raises(ScanError, match="displacement"):
        synthesize_scan(skin, np.zeros((3, 3)), cfg)


def test_scan_file_round_trip(skin, tmp_path):
    scan = synthesize_scan(skin, np.zeros_like(skin.points), ScannerConfig(n_points=5_000), seed=1)
    path = tmp_path / "scan.ply"
    write_scan(path, scan.points, scanner_pose=scan.scanner_pose, markers=scan.markers, marker_ids=scan.marker_ids,
               markers_nominal=scan.markers_nominal)  # fmt: skip
    back = read_scan(path)
    np.testing.assert_array_equal(back.points, scan.points)
    np.testing.assert_array_equal(back.scanner_pose, scan.scanner_pose)
    np.testing.assert_array_equal(back.markers, scan.markers)
    np.testing.assert_array_equal(back.markers_nominal, scan.markers_nominal)
    np.testing.assert_array_equal(back.marker_ids, scan.marker_ids)


def test_ply_reads_ascii_and_meshes(tmp_path):
    text = (
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float scalar_C2M_signed_distances\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n0 0 0 0.5\n1 0 0 -0.25\n0 1 0 1\n3 0 1 2\n"
    )
    path = tmp_path / "hand.ply"
    path.write_text(text)
    ply = read_ply(path)
    np.testing.assert_array_equal(ply.points, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(ply.triangles, [[0, 1, 2]])
    np.testing.assert_array_equal(ply.vertex_fields["scalar_C2M_signed_distances"], [0.5, -0.25, 1.0])
    assert ply.comments == ("made by hand",)
    binary = tmp_path / "mesh.ply"
    write_ply(binary, ply.points, triangles=ply.triangles, vertex_fields={"d": np.array([1.0, 2.0, 3.0])})
    again = read_ply(binary)
    np.testing.assert_array_equal(again.triangles, ply.triangles)
    np.testing.assert_array_equal(again.vertex_fields["d"], [1.0, 2.0, 3.0])


def test_ply_errors_name_the_problem(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_text("not a ply\n")
    with pytest.raises(ScanError, match="not a PLY"):
        read_ply(bad)
    with pytest.raises(ScanError, match="cannot open"):
        read_ply(tmp_path / "missing.ply")
    quads = tmp_path / "quads.ply"
    quads.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                     "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n"
                     "4 0 1 2 3\n")  # fmt: skip
    with pytest.raises(ScanError, match="triangles"):
        read_ply(quads)
    truncated = tmp_path / "short.ply"
    write_ply(truncated, np.zeros((100, 3)))
    truncated.write_bytes(truncated.read_bytes()[:-50])
    with pytest.raises(ScanError, match="truncated"):
        read_ply(truncated)


def test_cli_scan_writes_a_scan_that_gives_back_the_simulated_field(tmp_path, capsys):
    """`hood-decomp scan` on the built-in coarse hood, read back through the scan-file entry of the other verbs."""
    from hood_decomp.cli import main
    from hood_decomp.core.fe.ensemble import simulate_setting
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver
    from hood_decomp.io.model_files import load_model
    from hood_decomp.io.scans import field_from_scan_file

    assert main(["model", "--preset", "hood", "--resolution", "coarse", "--out", str(tmp_path / "m")]) == 0
    out = tmp_path / "scan.ply"
    code = main(["scan", "--model", str(tmp_path / "m"), "--set", "LOCK_L=1,HINGE_Y=-0.5", "--out", str(out),
                 "--points", "60000", "--noise-mm", "0.02", "--seed", "2"])  # fmt: skip
    assert code == 0 and out.exists() and out.with_suffix(".json").exists()
    model = load_model(tmp_path / "m")
    skin = skin_surface(model)
    truth = simulate_setting(build_solver(model), {"LOCK_L": 1.0, "HINGE_Y": -0.5}).normal_displacement
    field = field_from_scan_file(skin, out)
    assert field.coverage > 0.9
    # A coarse hood (about 35 mm spacing) smoothed over 2.5 spacings: a few hundredths of the 2 mm field at most.
    assert np.sqrt(np.nanmean((field.normal_displacement - truth) ** 2)) < 0.02
    capsys.readouterr()
    assert main(["scan", "--model", str(tmp_path / "m"), "--out", str(out), "--misplacement", "1,2"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "--misplacement" in error[0]
