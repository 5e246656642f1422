"""Multi-view parts (issue 17, "Must show"): coverage, accuracy and stated uncertainty of fused fields.

Truth: random parameter states in the declared ranges solved exactly by the bases' own FE model; each part is seen
in 3-5 partial views by the synthetic structured-light scanner (``fov_deg`` square field of view, aimed at different
parts of the skin from tilted robot poses; range noise 0.01-0.03 mm, 0.2 % outliers, 1 % dropouts, one hole; fixture
markers with 0.02 mm centre noise). The robot pose of each view is off its true pose by 0.05 mm / 0.005 deg; one view
per part is off by 2 mm / 0.2 deg (the markers must correct it). Each view is registered by its own markers and
fused (:func:`hood_decomp.core.scan.fusion.fuse_views`).

Reported:
- coverage: fused coverage against the union of the views' own coverages, and against the coverage of one field made
  from all views' points merged in the part frame at their *true* poses (a path that does not fuse);
- RMS parameter error (mm, against the effective truth) of the fused estimate and of each single view's estimate;
- the fraction of fused parameters inside their stated 95 % interval (|error| <= 1.96 std; parameters whose contact
  state the estimate got right, as bench_uncertainty), also with the one-pose summary of the registration errors the
  DisplacementField message carries (what the estimator node sees in an inspection);
- with ``--nodes``, the same parts through the real scan and estimator nodes (processes, Fast DDS on loopback): an
  InspectPart goal per part, each view's cloud (points and marker centres, metres) with its robot pose on scan/pose;
  the result's boundary state against the same truth (fraction inside the stated 95 % interval, max |error|/std) and
  its stds against the in-process (core path) stds of the same part;
- the pose-off view: its marker-fit pose error against the truth in units of the fit's stated pose std (per twist
  component, and Mahalanobis d2: with the marker noise estimated from the fit's residual, d2 / 6 ~ F(6, 3K - 6)),
  and the robot pose's error in the same units.

Prints a table and writes benchmarks/out/multiview.json (rewritten as it goes). Run from the repository root:
    scripts/with-env nice python benchmarks/bench_multiview.py [--parts 200] [--resolution coarse] [--points 60000]
        [--nodes]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from scipy.stats import f

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.method.bases import estimate_field  # noqa: E402
from hood_decomp.core.scan.fusion import ScanView, fuse_views  # noqa: E402
from hood_decomp.core.scan.scan_field import prepared_estimator  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, random_rigid, synthesize_scan  # noqa: E402
from tests.conftest import _hood_case  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "multiview.json"
Z95 = 1.959964
#: candidate views: aim (fractions of the half extents) and tilt (deg about the skin's principal axes)
VIEWS = (((-0.55, -0.45), (12.0, -12.0)), ((0.55, -0.45), (12.0, 12.0)), ((-0.55, 0.5), (-12.0, -12.0)),
         ((0.55, 0.5), (-12.0, 12.0)), ((0.0, 0.0), (0.0, 0.0)))


def log(line: str) -> None:
    print(f"[bench_multiview {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def pose_error_twist(estimated: np.ndarray, true: np.ndarray, center: np.ndarray) -> np.ndarray:
    """The error of ``estimated`` against ``true`` (4, 4, part <- scanner) as a twist [omega rad, t mm] about
    ``center``: x_est = x_true + omega x (x - center) + t to first order."""
    delta = estimated @ np.linalg.inv(true)
    cos = np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1)
    angle = np.arccos(cos)
    skew = (delta[:3, :3] - delta[:3, :3].T) / 2
    axis_sin = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    omega = axis_sin * (angle / np.sin(angle) if angle > 1e-12 else 1.0)
    t = delta[:3, :3] @ center + delta[:3, 3] - center
    return np.concatenate([omega, t])


class NodePath:
    """The scan and estimator nodes as processes serving ``bases_path``, with the fixture's markers as the cell
    calibration, and a plain rclpy InspectPart client: :meth:`send` a part's views, :meth:`result` its boundary
    state (values and stds, mm)."""

    def __init__(self, bases_path: Path, markers: dict[int, np.ndarray], directory: Path) -> None:
        from geometry_msgs.msg import TransformStamped
        from hood_decomp_msgs.action import InspectPart
        from rclpy.action import ActionClient
        from sensor_msgs.msg import PointCloud2

        from hood_decomp.ros import messages
        from hood_decomp.ros.launcher import start_nodes
        from hood_decomp.ros.participant import Participant

        _, marker_params = messages.calibration_to_params(np.eye(4), markers)
        params = directory / "params.yaml"
        params.write_text("hood_decomp_scan:\n  ros__parameters:\n"
                          f"    marker_positions: {json.dumps(marker_params)}\n    marker_field: marker_id\n"
                          "    result_timeout_s: 120.0\n")
        self.processes = start_nodes(bases_path, params_file=params, nodes=("scan_node", "estimator_node"),
                                     log_dir=directory)
        self.peer = Participant("bench_multiview")
        self.goal_type = InspectPart.Goal
        self.client = ActionClient(self.peer.node, InspectPart, "hood_decomp/inspect_part")
        self.clouds = self.peer.publisher("scan/points", PointCloud2)
        self.poses = self.peer.publisher("scan/pose", TransformStamped)
        if not (self.peer.connected(["scan/points", "scan/pose"], [], 90.0)
                and self.peer.wait(self.client.server_is_ready, 90.0)):
            raise RuntimeError(f"the scan node's InspectPart server did not come up in 90 s (logs in {directory})")

    def send(self, part: int, scans: list, poses: list[np.ndarray]) -> object:
        """An InspectPart goal of len(scans) views, then each view's robot pose and cloud; returns the goal."""
        from hood_decomp.ros.scan_bag import scan_cloud, transform_stamped

        sent = self.client.send_goal_async(self.goal_type(part_id=f"bench-{part}", expected_views=len(scans)))
        if not (self.peer.wait(sent.done, 30.0) and sent.result().accepted):
            raise RuntimeError(f"goal of part {part} not accepted")
        for k, (scan, pose) in enumerate(zip(scans, poses, strict=True)):
            stamp = (1000 + 10 * part + k) * 1_000_000_000
            self.poses.publish(transform_stamped("hood", f"camera_{k}", pose, stamp))
            self.peer.wait(lambda: False, 0.3)  # the pose first: the node looks it up when the cloud comes
            cloud = scan_cloud(scan, stamp)
            cloud.header.frame_id = f"camera_{k}"
            self.clouds.publish(cloud)
        return sent.result()

    def result(self, handle: object, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The part's boundary state: values, stds (mm) and lifted flags in the order ``names``."""
        future = handle.get_result_async()
        if not self.peer.wait(future.done, 600.0):
            raise RuntimeError("no InspectPart result in 600 s")
        result = future.result().result
        state = result.boundary_state
        if not result.success or tuple(state.names) != tuple(names):
            raise RuntimeError(f"inspection failed: {result.message}")
        return (np.asarray(state.values) * 1000.0, np.asarray(state.std_dev) * 1000.0,
                np.asarray(state.lifted, bool))

    def close(self) -> None:
        from hood_decomp.ros.launcher import stop_nodes

        self.client.destroy()
        self.peer.close()
        stop_nodes(self.processes)


@contextlib.contextmanager
def node_path(enabled: bool, bases_path: Path, skin, directory: Path, rng: np.random.Generator
              ) -> Iterator[NodePath | None]:
    """The running nodes when ``enabled`` (the fixture's markers found by a calibration pass of every candidate
    view), else None."""
    if not enabled:
        yield None
        return
    markers: dict[int, np.ndarray] = {}
    for aim, tilt in VIEWS:
        scan = synthesize_scan(skin, np.zeros((skin.n_nodes, 3)), ScannerConfig(
            n_points=2000, marker_noise_mm=0.0, view_center=aim, view_tilt_deg=tilt, fov_deg=40.0,
            standoff_mm=1500.0), seed=int(rng.integers(1 << 30)))
        markers.update({int(i): p for i, p in zip(scan.marker_ids, scan.markers_nominal, strict=True)})
    log(f"starting the scan and estimator nodes ({len(markers)} fixture markers)")
    nodes = NodePath(bases_path, markers, directory)
    try:
        yield nodes
    finally:
        nodes.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, default=200)
    parser.add_argument("--resolution", default="coarse", choices=("coarse", "default"))
    parser.add_argument("--points", type=int, default=60_000, help="scan points on the skin per view")
    parser.add_argument("--fov", type=float, default=40.0, help="full field-of-view angle of a view, deg")
    parser.add_argument("--seed", type=int, default=17)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--nodes", action="store_true",
                        help="also run each part through the scan and estimator nodes (InspectPart)")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    log(f"building the {args.resolution} hood, its ensemble and bases")
    with tempfile.TemporaryDirectory() as tmp:
        case = _hood_case(args.resolution, Path(tmp))
        with node_path(args.nodes, case.bases_path, case.skin, Path(tmp), np.random.default_rng(0)) as nodes:
            results = run_parts(args, rng, case, nodes)
    print_table(results["summary"], case.bases.names)
    return 0


def run_parts(args: argparse.Namespace, rng: np.random.Generator, case, nodes: NodePath | None) -> dict:
    """Run ``args.parts`` parts (module docstring); the results, summarised and saved every 10 parts."""
    bases, reduced, skin = case.bases, case.reduced, case.skin
    names, n_b = bases.names, case.reduced.n_bilateral
    lo, hi = bases.pca.lower_, bases.pca.upper_
    est = prepared_estimator(skin)
    results: dict = {"date": time.strftime("%Y-%m-%d"), "load": os.getloadavg()[0], "names": list(names),
                     "args": {k: str(v) for k, v in vars(args).items()}, "parts": []}

    def save() -> None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=1))

    start = time.time()
    for part in range(args.parts):
        member = solve_members(reduced, rng.uniform(lo, hi)[None])
        truth = member.effective[0]
        true_lifted = np.zeros(len(names), bool)
        true_lifted[n_b:] = member.contact_fraction[0] == 0.0
        n_views = int(rng.integers(3, 6))
        chosen = rng.permutation(len(VIEWS))[:n_views]
        off_view = int(rng.integers(n_views))
        views, scans = [], []
        for k, index in enumerate(chosen):
            aim, tilt = VIEWS[index]
            config = ScannerConfig(n_points=args.points, noise_mm=float(rng.uniform(0.01, 0.03)), marker_noise_mm=0.02,
                                   n_holes=1, view_center=aim, view_tilt_deg=tilt, fov_deg=args.fov,
                                   standoff_mm=1500.0, pose_error_deg=0.0, pose_error_mm=0.0)
            scan = synthesize_scan(skin, member.displacement[0], config, seed=int(rng.integers(1 << 30)))
            angle, shift = (0.2, 2.0) if k == off_view else (0.005, 0.05)
            pose = scan.true_transform @ random_rigid(rng, angle, shift)
            views.append(ScanView(scan.points, pose, scan.markers, scan.markers_nominal, name=f"view {k + 1}",
                                  pose_source="robot"))
            scans.append(scan)
        # the nodes work on the part while this process fuses it in-process (the core path)
        handle = None if nodes is None else nodes.send(part, scans, [v.scanner_pose for v in views])
        fused = fuse_views(skin, views, estimator=est)
        seen = np.array([np.isfinite(v.field.normal_displacement) for v in fused.views])
        union = float(seen.any(axis=0).mean())
        merged_coverage = None
        if nodes is None:  # an independent coverage check, skipped beside the nodes (one more scan step per part)
            merged_coverage = est.field(np.vstack([s.points @ s.true_transform[:3, :3].T + s.true_transform[:3, 3]
                                                   for s in scans])).coverage
        estimate = estimate_field(bases, fused.field)
        error = estimate.values - truth
        same = estimate.lifted == true_lifted
        z = np.where(same, error / estimate.std, np.nan)
        # what a node downstream sees: the DisplacementField message carries the one-pose summary, not the views'
        one_pose = estimate_field(bases, dataclasses.replace(fused.field, error_model=dataclasses.replace(
            fused.field.errors, view_poses=())))
        z_one_pose = np.where(one_pose.lifted == true_lifted, (one_pose.values - truth) / one_pose.std, np.nan)
        single = [estimate_field(bases, v.field) for v in fused.views]
        single_rms = [float(np.sqrt(np.mean((s.values - truth) ** 2))) for s in single]
        single_z = [np.where(s.lifted == true_lifted, (s.values - truth) / s.std, np.nan) for s in single]
        off = fused.views[off_view]
        covariance = off.registration.pose_covariance
        center = off.registration.pose_center
        fit_twist = pose_error_twist(off.registration.transform, scans[off_view].true_transform, center)
        robot_twist = pose_error_twist(views[off_view].scanner_pose, scans[off_view].true_transform, center)
        pose_std = np.sqrt(np.diag(covariance))
        node: dict = {}
        if handle is not None:
            values, std, lifted = nodes.result(handle, names)
            node = {"node_rms_mm": float(np.sqrt(np.mean((values - truth) ** 2))),
                    "node_z": [None if not (ok and np.isfinite(v)) else float(v)
                               for v, ok in zip((values - truth) / std, lifted == true_lifted, strict=True)],
                    "node_std_over_core": (std / estimate.std).tolist(),
                    "node_value_minus_core_mm": (values - estimate.values).tolist()}
        results["parts"].append({**node,
            "views": n_views, "markers": [v.registration.n_markers for v in fused.views], "off_view": off_view,
            "fused_coverage": fused.field.coverage, "union_coverage": union, "merged_coverage": merged_coverage,
            "view_coverage": [v.field.coverage for v in fused.views],
            "fused_rms_mm": float(np.sqrt(np.mean(error**2))), "single_rms_mm": single_rms,
            "z": [None if not np.isfinite(v) else float(v) for v in z],
            "z_one_pose": [None if not np.isfinite(v) else float(v) for v in z_one_pose],
            "single_z": [[None if not np.isfinite(v) else float(v) for v in sz] for sz in single_z],
            "pose_fit_z": (fit_twist / pose_std).tolist(), "pose_robot_z": (robot_twist / pose_std).tolist(),
            "pose_fit_d2": float(fit_twist @ np.linalg.solve(covariance, fit_twist)),
            "pose_correction_mm": off.pose_correction_mm, "pose_correction_deg": off.pose_correction_deg,
            "pose_std_mm": pose_std[3:].tolist(), "pose_std_deg": np.degrees(pose_std[:3]).tolist(),
        })
        if (part + 1) % 10 == 0 or part + 1 == args.parts:
            results["summary"] = summarise(results["parts"], names)
            save()
            s = results["summary"]
            log(f"part {part + 1}: {(time.time() - start) / (part + 1):.1f} s per part; fused RMS "
                f"{s['fused_rms_mm']:.4f} mm vs single {s['mean_single_rms_mm']:.4f} mm; inside 95 % "
                f"{s['inside_95']:.3f}" + (f", through the nodes {s['node_inside_95']:.3f}" if nodes else ""))
    return results


def summarise(parts: list[dict], names: tuple[str, ...]) -> dict:
    z = np.array([[np.nan if v is None else v for v in p["z"]] for p in parts])
    finite = np.isfinite(z)
    single_z = np.array([[np.nan if v is None else v for v in sz] for p in parts for sz in p["single_z"]])
    one_pose_z = np.array([[np.nan if v is None else v for v in p["z_one_pose"]] for p in parts])
    coverage_gap = np.array([p["fused_coverage"] - p["union_coverage"] for p in parts])
    merged_gap = np.array([p["merged_coverage"] - p["union_coverage"] for p in parts
                           if p["merged_coverage"] is not None] or [np.nan])
    fit_z = np.array([p["pose_fit_z"] for p in parts])
    d2 = np.array([p["pose_fit_d2"] for p in parts])
    # the fit's marker noise is estimated from its residual (3K - 6 dof), so d2 / 6 follows F(6, 3K - 6)
    dof = np.array([3 * p["markers"][p["off_view"]] - 6 for p in parts])
    nodes = {}
    if "node_z" in parts[0]:  # the same parts through the scan and estimator nodes
        node_z = np.array([[np.nan if v is None else v for v in p["node_z"]] for p in parts])
        node_finite = np.isfinite(node_z)
        ratio = np.array([p["node_std_over_core"] for p in parts])
        nodes = {
            "node_inside_95": float(np.mean(np.abs(node_z[node_finite]) <= Z95)), "node_n_z": int(node_finite.sum()),
            "node_inside_95_per_parameter": {name: float(np.mean(np.abs(node_z[node_finite[:, k], k]) <= Z95))
                                             for k, name in enumerate(names)},
            "node_max_abs_z_per_parameter": {name: float(np.max(np.abs(node_z[node_finite[:, k], k])))
                                             for k, name in enumerate(names)},
            "core_max_abs_z_per_parameter": {name: float(np.max(np.abs(z[finite[:, k], k])))
                                             for k, name in enumerate(names)},
            "node_rms_mm": float(np.mean([p["node_rms_mm"] for p in parts])),
            "node_std_over_core_median": float(np.median(ratio)),
            "node_std_over_core_range": [float(ratio.min()), float(ratio.max())],
            "node_minus_core_max_abs_mm": float(np.max(np.abs([p["node_value_minus_core_mm"] for p in parts]))),
        }
    return {
        **nodes,
        "n_parts": len(parts), "views": np.bincount([p["views"] for p in parts], minlength=6)[3:].tolist(),
        "max_abs_fused_minus_union": float(np.max(np.abs(coverage_gap))),
        "max_abs_merged_minus_union": float(np.max(np.abs(merged_gap))),
        "mean_union_coverage": float(np.mean([p["union_coverage"] for p in parts])),
        "mean_view_coverage": float(np.mean([c for p in parts for c in p["view_coverage"]])),
        "fused_rms_mm": float(np.mean([p["fused_rms_mm"] for p in parts])),
        "mean_single_rms_mm": float(np.mean([r for p in parts for r in p["single_rms_mm"]])),
        "fused_rms_pooled_mm": float(np.sqrt(np.mean([p["fused_rms_mm"] ** 2 for p in parts]))),
        "single_rms_pooled_mm": float(np.sqrt(np.mean([r**2 for p in parts for r in p["single_rms_mm"]]))),
        "parts_fused_better_than_mean_single": float(np.mean([p["fused_rms_mm"] < np.mean(p["single_rms_mm"])
                                                              for p in parts])),
        "inside_95": float(np.mean(np.abs(z[finite]) <= Z95)), "n_z": int(finite.sum()),
        "one_pose_inside_95": float(np.nanmean(np.abs(one_pose_z[np.isfinite(one_pose_z)]) <= Z95)),
        "single_inside_95": float(np.mean(np.abs(single_z[np.isfinite(single_z)]) <= Z95)),
        "inside_95_per_parameter": {name: float(np.mean(np.abs(z[finite[:, k], k]) <= Z95))
                                    for k, name in enumerate(names)},
        "pose_fit_max_abs_z": float(np.max(np.abs(fit_z))),
        "pose_fit_within_3_std": float(np.mean(np.all(np.abs(fit_z) <= 3.0, axis=1))),
        "pose_fit_d2_p95_rate": float(np.mean(d2 / 6 <= f.ppf(0.95, 6, dof))),
        "pose_robot_min_max_abs_z": float(np.min(np.max(np.abs(np.array([p["pose_robot_z"] for p in parts])),
                                                        axis=1))),
        "median_pose_std_mm": float(np.median([np.linalg.norm(p["pose_std_mm"]) for p in parts])),
        "median_pose_std_deg": float(np.median([np.linalg.norm(p["pose_std_deg"]) for p in parts])),
    }


def print_table(s: dict, names: tuple[str, ...]) -> None:
    rows = [
        ("parts (3 / 4 / 5 views)", f"{s['n_parts']} ({' / '.join(map(str, s['views']))})"),
        ("mean view coverage / union", f"{s['mean_view_coverage']:.3f} / {s['mean_union_coverage']:.3f}"),
        ("max |fused - union| coverage", f"{s['max_abs_fused_minus_union']:.4f}"),
        ("max |merged cloud - union| coverage", f"{s['max_abs_merged_minus_union']:.4f}"),
        ("RMS parameter error fused / mean single view (mm)",
         f"{s['fused_rms_mm']:.4f} / {s['mean_single_rms_mm']:.4f}"),
        ("pooled RMS fused / single (mm)", f"{s['fused_rms_pooled_mm']:.4f} / {s['single_rms_pooled_mm']:.4f}"),
        ("parts where fused beats its views' mean", f"{s['parts_fused_better_than_mean_single']:.3f}"),
        ("fused inside stated 95 % interval", f"{s['inside_95']:.3f} (n = {s['n_z']})"),
        *((f"  {name}", f"{s['inside_95_per_parameter'][name]:.3f}") for name in names),
        ("single views inside their stated 95 % interval (control)", f"{s['single_inside_95']:.3f}"),
        ("fused, one-pose summary only (the message before it carried the views), inside 95 %",
         f"{s['one_pose_inside_95']:.3f}"),
        *((("through the nodes: inside stated 95 % interval", f"{s['node_inside_95']:.3f} (n = {s['node_n_z']})"),
           *((f"  {name}: nodes / core inside 95 %; max |z| nodes / core",
              f"{s['node_inside_95_per_parameter'][name]:.3f} / {s['inside_95_per_parameter'][name]:.3f}; "
              f"{s['node_max_abs_z_per_parameter'][name]:.2f} / {s['core_max_abs_z_per_parameter'][name]:.2f}")
             for name in names),
           ("through the nodes: stated std / core std, median (min-max)",
            f"{s['node_std_over_core_median']:.4f} ({s['node_std_over_core_range'][0]:.4f}-"
            f"{s['node_std_over_core_range'][1]:.4f})"),
           ("through the nodes: max |value - core value| (mm)", f"{s['node_minus_core_max_abs_mm']:.5f}"),
           ("through the nodes: RMS parameter error (mm)", f"{s['node_rms_mm']:.4f}"))
          if "node_inside_95" in s else ()),
        ("pose-off view: fit error max |z| / all |z| <= 3", f"{s['pose_fit_max_abs_z']:.2f} / "
                                                           f"{s['pose_fit_within_3_std']:.3f}"),
        ("pose-off view: Mahalanobis inside 95 % (F(6, 3K-6))", f"{s['pose_fit_d2_p95_rate']:.3f}"),
        ("pose-off view: robot pose error, smallest max |z|", f"{s['pose_robot_min_max_abs_z']:.0f}"),
        ("marker fit pose std (median |t| mm, |omega| deg)",
         f"{s['median_pose_std_mm']:.4f}, {s['median_pose_std_deg']:.5f}"),
    ]
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        print(f"{key:<{width}}  {value}")


if __name__ == "__main__":
    raise SystemExit(main())
