"""Latency of a multi-view inspection (issue 17): from the last view of a part to the InspectPart result.

The scan and estimator nodes as processes (Fast DDS, loopback) on the default hood; per part four partial views of
``--points`` points each (poses on scan/pose, markers in the clouds), an InspectPart goal of four views sent first;
the clock runs from publishing the last cloud to the result (the last view's field, the fusion, the fused field's
publication, the estimator's state and correction). Prints a table and writes benchmarks/out/inspection.json:
    scripts/with-env nice python benchmarks/bench_inspection.py [--parts 5] [--points 500000]
The same inspections run after the single-view latencies in one command with the three nodes:
``benchmarks/bench_nodes.py --inspection-parts 5`` (benchmarks/RESULTS.md).
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

from geometry_msgs.msg import TransformStamped  # noqa: E402
from hood_decomp_msgs.action import InspectPart  # noqa: E402
from rclpy.action import ActionClient  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from hood_decomp.ros import messages  # noqa: E402
from hood_decomp.ros.launcher import start_nodes, stop_nodes  # noqa: E402
from hood_decomp.ros.participant import Participant  # noqa: E402
from hood_decomp.ros.scan_bag import scan_cloud, transform_stamped  # noqa: E402
from tests.conftest import _hood_case  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "inspection.json"
VIEWS = (((-0.55, -0.45), (12.0, -12.0)), ((0.55, -0.45), (12.0, 12.0)), ((-0.55, 0.5), (-12.0, -12.0)),
         ((0.55, 0.5), (-12.0, 12.0)))


def log(line: str) -> None:
    print(f"[bench_inspection {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def inspection_views(skin, displacement: np.ndarray, points: int) -> list:
    """Four partial views (:data:`VIEWS`) of ``points`` points each of the part ``displacement`` (N, 3) mm."""
    from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan

    return [synthesize_scan(skin, displacement, ScannerConfig(
        n_points=points, noise_mm=0.02, marker_noise_mm=0.01, n_holes=1, view_center=aim, view_tilt_deg=tilt,
        fov_deg=40.0, standoff_mm=1500.0), seed=k) for k, (aim, tilt) in enumerate(VIEWS)]


def inspect_parts(peer, scans: list, parts: int, first_sec: int = 1000) -> tuple[list[float], list[dict]]:
    """``parts`` inspections of the four views ``scans`` through the running scan and estimator nodes, each an
    InspectPart goal of four views, three views sent 3 s apart, then the last; per part the seconds from publishing
    the last cloud to the result, and the result's success, message and coverage."""
    client = ActionClient(peer.node, InspectPart, "hood_decomp/inspect_part")
    clouds = peer.publisher("scan/points", PointCloud2)
    poses = peer.publisher("scan/pose", TransformStamped)
    if not (peer.connected(["scan/points", "scan/pose"], [], 90.0) and peer.wait(client.server_is_ready, 90)):
        raise RuntimeError("the InspectPart server or the scan node did not come up in 90 s")
    latencies, results = [], []
    for part in range(parts):
        sent = client.send_goal_async(InspectPart.Goal(part_id=f"bench-{part}", expected_views=4))
        if not (peer.wait(sent.done, 30.0) and sent.result().accepted):
            raise RuntimeError(f"goal of part {part} not accepted")
        for k, scan in enumerate(scans):
            stamp = (first_sec + 10 * part + k) * 1_000_000_000
            cloud = scan_cloud(scan, stamp)
            cloud.header.frame_id = f"camera_{k}"
            poses.publish(transform_stamped("hood", f"camera_{k}", scan.true_transform, stamp))
            if k < 3:
                clouds.publish(cloud)
                peer.wait(lambda: False, 3.0)  # the node takes the view before the last one comes
            else:
                peer.wait(lambda: False, 0.2)
                start = time.perf_counter()
                clouds.publish(cloud)
                future = sent.result().get_result_async()
        if not peer.wait(future.done, 120.0):
            raise RuntimeError(f"no result for part {part} in 120 s")
        latencies.append(time.perf_counter() - start)
        result = future.result().result
        results.append({"success": result.success, "message": result.message, "coverage": result.coverage})
        log(f"part {part}: {latencies[-1]:.3f} s from the last view to the result ({result.message})")
    client.destroy()
    return latencies, results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, default=5)
    parser.add_argument("--points", type=int, default=500_000)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    from hood_decomp.core.fe.ensemble import solve_members

    log("building the default hood, its ensemble and bases")
    tmp = Path(tempfile.mkdtemp(prefix="bench_inspection_"))
    case = _hood_case("default", tmp)
    rng = np.random.default_rng(17)
    member = solve_members(case.reduced, rng.uniform(case.bases.pca.lower_, case.bases.pca.upper_)[None])
    log(f"scanning four views of {args.points} points")
    scans = inspection_views(case.skin, member.displacement[0], args.points)
    _, markers = messages.calibration_to_params(np.eye(4), {int(i): p for s in scans
                                                            for i, p in zip(s.marker_ids, s.markers_nominal,
                                                                            strict=True)})
    params = tmp / "params.yaml"
    params.write_text("hood_decomp_scan:\n  ros__parameters:\n"
                      f"    marker_positions: {json.dumps(markers)}\n    marker_field: marker_id\n")
    processes = start_nodes(case.bases_path, params_file=params, nodes=("scan_node", "estimator_node"),
                            log_dir=tmp)
    try:
        with Participant("bench_inspection") as peer:
            latencies, results = inspect_parts(peer, scans, args.parts)
    finally:
        stop_nodes(processes)
        shutil.rmtree(tmp, ignore_errors=True)
    summary = {"date": time.strftime("%Y-%m-%d"), "load": os.getloadavg()[0], "points_per_view": args.points,
               "skin_nodes": case.skin.n_nodes, "latency_s": latencies, "median_s": float(np.median(latencies)),
               "max_s": float(np.max(latencies)), "results": results}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=1))
    print(f"{'parts':<32} {len(latencies)}")
    print(f"{'views x points':<32} 4 x {args.points:,}")
    print(f"{'last view -> result, median':<32} {summary['median_s']:.3f} s")
    print(f"{'last view -> result, max':<32} {summary['max_s']:.3f} s")
    print(f"{'load average at the end':<32} {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
