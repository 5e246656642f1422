"""Scan -> displacement field at the paper's resolution, against synthetic truth and against CloudCompare.

A crowned open skin of 188,871 nodes (the paper's visible skin has 188,559) carries a smooth boundary-effect-like
normal displacement (about 1.3 mm peak); the synthetic structured-light scanner takes about 1,000,000 points of it
(plus fixture background and outliers) at 0.02 and 0.05 mm range noise. Measured:

- field_from_scan (markers registration + node field) time and RMS error on seen nodes, free-edge row, near-edge
  band and interior separately, coverage, noise estimate;
- CloudCompare 2.11 cloud-to-mesh distance, like with like: (a) per scan point against the nominal skin mesh vs our
  per-point signed distance; (b) per skin node against the meshed scan (the paper's use) vs our node field, both
  against the truth; wall time of each side.

Prints a table and writes benchmarks/out/bench_scan.json. Run from the repository root:
    PYTHONPATH=ros2_ws/src/hood_decomp .venv/bin/python benchmarks/bench_scan.py [--repeats 3] [--no-cloudcompare]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan  # noqa: E402
from hood_decomp.io.ply import write_ply, write_skin_mesh  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402
from tests.skins import (  # noqa: E402
    CLOUDCOMPARE,
    along_normals,
    boundary_nodes,
    cloudcompare_c2m,
    crowned_patch,
    mesh_scan_2p5d,
    near_edge,
    smooth_field,
)


def rms(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def log(line: str) -> None:
    print(f"[bench_scan {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed repetitions of field_from_scan (median)")
    parser.add_argument("--no-cloudcompare", action="store_true")
    parser.add_argument("--points", type=int, default=1_000_000, help="target scan points on the skin")
    parser.add_argument("--hood", default="default", choices=("none", "coarse", "default", "paper"),
                        help="also scan the built-in hood at this resolution (a forward FE solve as truth)")
    args = parser.parse_args()

    skin = crowned_patch(471, 401)
    truth = smooth_field(skin, amplitude_mm=1.0)
    edge_row = boundary_nodes(skin)
    band = near_edge(skin, 10.0) & ~edge_row
    interior = ~near_edge(skin, 10.0)
    log(f"skin {skin.n_nodes} nodes, truth peak {np.abs(truth).max():.3f} mm")
    start = time.perf_counter()
    estimator = ScanFieldEstimator().fit(skin)
    fit_s = time.perf_counter() - start
    log(f"estimator prepared in {fit_s:.2f} s (radius {estimator.radius_mm_:.2f} mm)")
    results: dict = {
        "skin_nodes": skin.n_nodes,
        "radius_mm": estimator.radius_mm_,
        "prepare_s": fit_s,
        "load_average_1min_at_start": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
        "noise": {},
    }
    scans = {}
    for noise in (0.02, 0.05):
        start = time.perf_counter()
        scan = synthesize_scan(skin, along_normals(skin, truth), ScannerConfig(n_points=args.points, noise_mm=noise), 7)
        scan_s = time.perf_counter() - start
        scans[noise] = scan
        log(f"noise {noise}: {scan.points.shape[0]} points ({scan.n_skin_points} on the skin) in {scan_s:.1f} s")
        kwargs = {"markers_mm": scan.markers, "markers_nominal_mm": scan.markers_nominal, "estimator": estimator}
        field_from_scan(skin, scan.points, **kwargs)  # warm-up (page faults of the first touch)
        times, cpu = [], []
        for _ in range(args.repeats):
            start, start_cpu = time.perf_counter(), time.process_time()
            field, registration = field_from_scan(skin, scan.points, **kwargs)
            times.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
        error = field.normal_displacement - truth
        results["noise"][str(noise)] = {
            "scan_points": int(scan.points.shape[0]),
            "scan_points_on_skin": scan.n_skin_points,
            "synthesize_s": scan_s,
            "field_from_scan_s_median": float(np.median(times)),
            "field_from_scan_s_min": float(np.min(times)),
            "field_from_scan_cpu_s_median": float(np.median(cpu)),
            "rms_error_mm": rms(error),
            "rms_error_edge_row_mm": rms(error[edge_row]),
            "rms_error_edge_band_mm": rms(error[band]),
            "rms_error_interior_mm": rms(error[interior]),
            "max_abs_error_mm": float(np.nanmax(np.abs(error))),
            "coverage": field.coverage,
            "noise_rms_estimate_mm": field.noise_rms,
            "registration": registration.method,
            "marker_rms_mm": registration.marker_rms_mm,
        }
        log(f"noise {noise}: {results['noise'][str(noise)]}")

    if args.hood != "none":
        results["hood"] = hood_case(args.hood, args.points)
    if not args.no_cloudcompare:
        if shutil.which(CLOUDCOMPARE) is None:
            results["cloudcompare"] = "not installed (apt-get install cloudcompare)"
        else:
            results["cloudcompare"] = compare_with_cloudcompare(skin, truth, estimator, scans[0.05])
    results["load_average_1min_at_end"] = os.getloadavg()[0]
    out = ROOT / "benchmarks" / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_scan.json").write_text(json.dumps(results, indent=2))
    print_table(results)
    return 0


def hood_case(resolution: str, n_points: int) -> dict:
    """The built-in hood: LOCK_L = 1, HINGE_X = -0.5, BUFFER_R = 0.5 mm solved by the embedded FE solver (truth: its
    skin normal displacement u.n, with in-plane motion from the hinge), scanned, turned back into a field."""
    from hood_decomp.core.fe.ensemble import simulate_setting
    from hood_decomp.core.fe.hood_preset import build_hood
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver

    model = build_hood(resolution)
    skin = skin_surface(model)
    setting = {"LOCK_L": 1.0, "HINGE_X": -0.5, "BUFFER_R": 0.5}
    log(f"hood {resolution}: {skin.n_nodes} skin nodes, solving {setting}")
    solved = simulate_setting(build_solver(model), setting)
    estimator = ScanFieldEstimator().fit(skin)
    edge_row = boundary_nodes(skin)
    report: dict = {"resolution": resolution, "skin_nodes": skin.n_nodes, "setting_mm": setting,
                    "truth_peak_mm": float(np.abs(solved.normal_displacement).max()),
                    "radius_mm": estimator.radius_mm_, "noise": {}}  # fmt: skip
    for noise in (0.02, 0.05):
        scan = synthesize_scan(skin, solved.displacement, ScannerConfig(n_points=n_points, noise_mm=noise), 3)
        kwargs = {"markers_mm": scan.markers, "markers_nominal_mm": scan.markers_nominal, "estimator": estimator}
        field_from_scan(skin, scan.points, **kwargs)
        start = time.perf_counter()
        field, _ = field_from_scan(skin, scan.points, **kwargs)
        elapsed = time.perf_counter() - start
        error = field.normal_displacement - solved.normal_displacement
        report["noise"][str(noise)] = {
            "scan_points": int(scan.points.shape[0]),
            "field_from_scan_s": elapsed,
            "rms_error_mm": rms(error),
            "rms_error_edge_row_mm": rms(error[edge_row]),
            "rms_error_interior_mm": rms(error[~edge_row]),
            "max_abs_error_mm": float(np.nanmax(np.abs(error))),
            "coverage": field.coverage,
            "noise_rms_estimate_mm": field.noise_rms,
        }
        log(f"hood {resolution} noise {noise}: {report['noise'][str(noise)]}")
    return report


def compare_with_cloudcompare(skin, truth, estimator, scan) -> dict:
    """Both CloudCompare comparisons on the registered 0.05 mm scan (same points, same frame for both sides)."""
    _, registration = field_from_scan(
        skin, scan.points, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal, estimator=estimator
    )
    transform = registration.transform
    points = scan.points @ transform[:3, :3].T + transform[:3, 3]
    report: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        # (a) per scan point -> nominal skin mesh.
        start = time.perf_counter()
        located = estimator.point_distances(points)
        ours_s = time.perf_counter() - start
        write_ply(tmp_path / "cloud.ply", points)
        write_skin_mesh(tmp_path / "skin.ply", skin)
        log("CloudCompare: scan points -> nominal skin mesh")
        theirs, wall, reported = cloudcompare_c2m(str(tmp_path / "cloud.ply"), str(tmp_path / "skin.ply"),
                                                  str(tmp_path / "out_a.ply"))  # fmt: skip
        inner = located.node >= 0
        inner[inner] = ~boundary_nodes(skin)[located.node[inner]]
        diff = located.distance[inner] - theirs[inner]
        report["per_point"] = {
            "points_compared": int(inner.sum()),
            "mean_diff_mm": float(np.mean(diff)),
            "std_diff_mm": float(np.std(diff)),
            "max_abs_diff_mm": float(np.max(np.abs(diff))),
            "ours_s": ours_s,
            "cloudcompare_wall_s": wall,
            "cloudcompare_reported_compute_s": reported,
        }
        log(f"per point: {report['per_point']}")
        # (b) per skin node -> meshed scan (the paper's use); the scan meshed here (Debian's CloudCompare has no CGAL).
        on_skin = points[located.node >= 0]
        start = time.perf_counter()
        triangles = mesh_scan_2p5d(on_skin, max_edge_mm=3.0 * estimator.spacing_mm_)
        mesh_s = time.perf_counter() - start
        write_ply(tmp_path / "scan_mesh.ply", on_skin, triangles=triangles)
        write_ply(tmp_path / "nodes.ply", skin.points)
        log("CloudCompare: skin nodes -> meshed scan")
        to_scan, wall_b, reported_b = cloudcompare_c2m(str(tmp_path / "nodes.ply"), str(tmp_path / "scan_mesh.ply"),
                                                       str(tmp_path / "out_b.ply"))  # fmt: skip
        start = time.perf_counter()
        ours = field_from_scan(
            skin, scan.points, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal, estimator=estimator
        )[0].normal_displacement
        ours_b_s = time.perf_counter() - start
        theirs_b = -to_scan
        both = np.isfinite(ours) & ~boundary_nodes(skin) & (np.abs(to_scan) < 2.0)
        report["per_node"] = {
            "nodes_compared": int(both.sum()),
            "ours_rms_error_mm": rms(ours[both] - truth[both]),
            "cloudcompare_rms_error_mm": rms(theirs_b[both] - truth[both]),
            "cloudcompare_median_abs_error_mm": float(np.median(np.abs(theirs_b[both] - truth[both]))),
            "median_diff_cloudcompare_minus_ours_mm": float(np.median(theirs_b[both] - ours[both])),
            "ours_field_from_scan_s": ours_b_s,
            "scan_meshing_s": mesh_s,
            "cloudcompare_wall_s": wall_b,
            "cloudcompare_reported_compute_s": reported_b,
        }
        log(f"per node: {report['per_node']}")
    return report


def print_table(results: dict) -> None:
    print(f"\nScan -> field, {results['skin_nodes']} skin nodes, radius {results['radius_mm']:.2f} mm, preparation "
          f"{results['prepare_s']:.2f} s (once per skin); load average {results['load_average_1min_at_start']:.2f} -> "
          f"{results['load_average_1min_at_end']:.2f} on {results['cpu_count']} cores")  # fmt: skip
    header = ("noise mm", "points", "wall s", "cpu s", "rms", "edge row", "edge band", "interior", "max", "coverage",
              "noise est")  # fmt: skip
    print(" ".join(f"{h:>9}" for h in header))
    for noise, r in results["noise"].items():
        row = (noise, r["scan_points"], r["field_from_scan_s_median"], r["field_from_scan_cpu_s_median"],
               r["rms_error_mm"], r["rms_error_edge_row_mm"], r["rms_error_edge_band_mm"], r["rms_error_interior_mm"],
               r["max_abs_error_mm"], r["coverage"], r["noise_rms_estimate_mm"])  # fmt: skip
        print(" ".join(f"{v:>9}" if isinstance(v, str | int) else f"{v:>9.4f}" for v in row))
    hood = results.get("hood")
    if hood:
        print(f"\nBuilt-in hood ({hood['resolution']}, {hood['skin_nodes']} skin nodes, radius "
              f"{hood['radius_mm']:.1f} mm), FE solve {hood['setting_mm']} as truth "
              f"(peak {hood['truth_peak_mm']:.2f} mm)")
        print(" ".join(f"{h:>9}" for h in ("noise mm", "points", "wall s", "rms", "edge row", "interior", "max",
                                            "coverage", "noise est")))  # fmt: skip
        for noise, r in hood["noise"].items():
            row = (noise, r["scan_points"], r["field_from_scan_s"], r["rms_error_mm"], r["rms_error_edge_row_mm"],
                   r["rms_error_interior_mm"], r["max_abs_error_mm"], r["coverage"], r["noise_rms_estimate_mm"])
            print(" ".join(f"{v:>9}" if isinstance(v, str | int) else f"{v:>9.4f}" for v in row))
    cc = results.get("cloudcompare")
    if isinstance(cc, dict):
        a, b = cc["per_point"], cc["per_node"]
        print("\nCloudCompare 2.11 C2M vs hood_decomp (0.05 mm scan, the same registered points for both)")
        print(f"{'comparison':<32} {'ours s':>8} {'CC wall s':>10} {'CC compute s':>13}  agreement")
        print(f"{'per point -> nominal mesh':<32} {a['ours_s']:>8.3f} {a['cloudcompare_wall_s']:>10.2f} "
              f"{a['cloudcompare_reported_compute_s']:>13.2f}  ours - CC: mean {a['mean_diff_mm']:.1e}, "
              f"std {a['std_diff_mm']:.1e} mm over {a['points_compared']} points")  # fmt: skip
        print(f"{'per node -> meshed scan (paper)':<32} {b['ours_field_from_scan_s']:>8.3f} "
              f"{b['cloudcompare_wall_s']:>10.2f} {b['cloudcompare_reported_compute_s']:>13.2f}  median CC - ours "
              f"{b['median_diff_cloudcompare_minus_ours_mm']:.1e} mm over {b['nodes_compared']} nodes")  # fmt: skip
        print(f"per node RMS error vs truth: ours {b['ours_rms_error_mm']:.4f} mm, CloudCompare "
              f"{b['cloudcompare_rms_error_mm']:.4f} mm (median |error| {b['cloudcompare_median_abs_error_mm']:.4f}); "
              f"meshing the scan for CloudCompare: {b['scan_meshing_s']:.1f} s, not in its time")  # fmt: skip
    elif cc is not None:
        print(f"\nCloudCompare: {cc}")


if __name__ == "__main__":
    sys.exit(main())
