"""Benchmark: end-to-end latency of the three nodes (real processes, Fast DDS on loopback) and a sustained run.

Latency: from a 1,000,000-point scan published on scan/points to its boundary state received, and to its effect
fields received (targets at paper resolution: under 1 s and under 1.5 s). Sustained: one scan per second for
--soak-seconds, counting lost scans and sampling the nodes' resident memory (target: none lost, no growth).
Best effort (issue 17): --best-effort N clouds from a best-effort publisher (the sensor-data QoS of common scanner
drivers), each sent when the previous one was answered; target: N of N delivered and answered.

    scripts/with-env python benchmarks/bench_nodes.py --resolution default [--soak-seconds 300] [--best-effort 100]

Latency is reported for the first scan (the nodes just activated) and as the median and max over all scans, and the
boundary state's split into the scan node's and the estimator's handler times (their OK diagnostics' ``seconds``)
and the rest (transport of the cloud and the field, executor wake-ups). With
--inspection-parts N the same nodes then serve N four-view inspections of --inspection-points points per view
(benchmarks/bench_inspection.py, last view to the InspectPart result), so one command gives both of issue 17's
latency figures:

    scripts/with-env python benchmarks/bench_nodes.py --resolution default --scans 10 --inspection-parts 5

Bases are built once per resolution and cached in benchmarks/out/cache_<resolution>/. Prints a table and writes
benchmarks/out/bench_nodes_<resolution>.json.
"""

from __future__ import annotations

import argparse
import array
import json
import logging
import pathlib
import platform
import statistics
import sys
import time

import numpy as np
import psutil
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from hood_decomp_msgs.msg import BoundaryState, EffectFields
from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2

from hood_decomp.ros.launcher import start_nodes, stop_nodes
from hood_decomp.ros.participant import Participant, latest_heartbeat
from hood_decomp.ros.scan_bag import scan_cloud, write_node_params
from hood_decomp.synthetic.scanner import ScannerConfig
from hood_decomp.synthetic.scenarios import make_scenario_scan

OUT = pathlib.Path(__file__).parent / "out"


def log(line: str) -> None:
    print(f"[bench_nodes {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def log_library_progress() -> None:
    """The package's progress (its INFO log records) on stderr, formatted like :func:`log`."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[bench_nodes %(asctime)s] %(message)s", "%H:%M:%S"))
    package = logging.getLogger("hood_decomp")
    package.addHandler(handler)
    package.setLevel(logging.INFO)


def prepared(resolution: str):
    """(skin, solver, reduced, bases path), building and caching the ensemble and bases when missing."""
    from hood_decomp.core.fe.hood_preset import build_hood
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.method.bases import build_bases
    from hood_decomp.io.bases import save_bases
    from hood_decomp.io.ensemble_store import load_ensemble, write_ensemble

    cache = OUT / f"cache_{resolution}"
    cache.mkdir(parents=True, exist_ok=True)
    model = build_hood(resolution)
    skin = skin_surface(model)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    bases_path = cache / "bases.h5"
    if not bases_path.exists():
        ensemble_path = cache / "ensemble.h5"
        if not ensemble_path.exists():
            write_ensemble(ensemble_path, reduced, skin, model.lower, model.upper, n_validation=0)
        save_bases(bases_path, build_bases(load_ensemble(ensemble_path), skin, reduced))
    return skin, solver, reduced, bases_path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", default="default", choices=("coarse", "default", "paper"))
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--scans", type=int, default=10, help="scans for the latency figures")
    parser.add_argument("--gap-s", type=float, default=0.0,
                        help="idle seconds between the latency scans (a cell's takt: caches go cold between parts)")
    parser.add_argument("--soak-seconds", type=float, default=0.0, help="length of the one-scan-per-second run")
    parser.add_argument("--best-effort", type=int, default=0,
                        help="also send this many clouds from a best-effort publisher, one per answer")
    parser.add_argument("--inspection-parts", type=int, default=0,
                        help="then this many four-view inspections through the InspectPart action")
    parser.add_argument("--inspection-points", type=int, default=500_000, help="points per inspection view")
    parser.add_argument("--oversize-points", type=int, default=0,
                        help="also send one cloud of this many points (e.g. 20000000) and check it is refused")
    args = parser.parse_args()
    log_library_progress()
    skin, solver, reduced, bases_path = prepared(args.resolution)
    rng = np.random.default_rng(0)
    scans = [make_scenario_scan(f"s{i}", solver, reduced, skin,
                                dict(zip(reduced.names, rng.uniform(-0.8, 0.8, len(reduced.names)), strict=True)),
                                ScannerConfig(n_points=args.points, noise_mm=0.02), seed=i) for i in range(3)]
    clouds = [scan_cloud(s.scan, 0) for s in scans]
    views = []
    if args.inspection_parts:
        from bench_inspection import inspection_views

        from hood_decomp.core.fe.ensemble import solve_members

        state = rng.uniform(-0.8, 0.8, len(reduced.names))
        views = inspection_views(skin, solve_members(reduced, state[None]).displacement[0], args.inspection_points)
    params = write_node_params(OUT / f"params_{args.resolution}.yaml", {
        "scanner_pose_mm": scans[0].scan.scanner_pose.tolist(),
        "marker_positions_mm": {str(int(i)): p.tolist() for s in [*(s.scan for s in scans), *views] for i, p in
                                zip(s.marker_ids, s.markers_nominal, strict=True)}})
    processes = start_nodes(bases_path.resolve(), params_file=params, log_dir=OUT)
    peer = Participant("bench_nodes", depth=100)
    peer.publisher("scan/points", PointCloud2)
    best_effort_pub = peer.node.create_publisher(PointCloud2, "scan/points", qos_profile_sensor_data)
    diagnostics = peer.collect("/diagnostics", DiagnosticArray)
    arrival: dict[tuple[str, int], float] = {}

    def stamp_of(msg) -> int:
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    for topic in ("hood_decomp/boundary_state", "hood_decomp/effects"):
        peer.subscribe(topic, BoundaryState if topic.endswith("state") else EffectFields,
                       lambda msg, t=topic: arrival.setdefault((t, stamp_of(msg)), time.perf_counter()))
    try:
        if not peer.connected(["scan/points"], ["hood_decomp/boundary_state", "hood_decomp/effects"], 300) or not \
                peer.wait(lambda: int(latest_heartbeat(diagnostics, "hood_decomp_scan").get("publishers /scan/points",
                                                                                            0)) >= 2, 60):
            raise RuntimeError("the nodes did not come up (or match both scan publishers) in time; logs in "
                               "benchmarks/out/")
        sent: dict[int, float] = {}

        def publish(index: int, stamp: int) -> None:
            cloud = clouds[index % len(clouds)]
            cloud.header.stamp = Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
            sent[stamp] = time.perf_counter()
            peer.publishers["scan/points"].publish(cloud)

        def answered(stamp: int) -> bool:
            return ("hood_decomp/effects", stamp) in arrival and ("hood_decomp/boundary_state", stamp) in arrival

        def refused(stamp: int) -> list[str]:
            key = f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}"
            return [f"{s.name}: {s.message}" for array in diagnostics for s in array.status
                    if s.level == DiagnosticStatus.ERROR and any(v.key == "stamp" and v.value == key
                                                                 for v in s.values)]

        def node_seconds(stamp: int, node: str) -> float:
            """The node's handler time for this stamp (its OK diagnostic's ``seconds``), NaN if not (yet) seen."""
            key = f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}"
            for array in diagnostics:
                for s in array.status:
                    values = {v.key: v.value for v in s.values}
                    if s.name == f"hood_decomp/{node}" and values.get("stamp") == key and "seconds" in values:
                        return float(values["seconds"])
            return float("nan")

        latencies = {"boundary_state": [], "effects": []}
        handler = {"scan": [], "estimator": []}
        for i in range(args.scans):  # one at a time: latency, not queueing
            stamp = 1_000_000_000 * (i + 1)
            publish(i, stamp)
            if not peer.wait(lambda s=stamp: answered(s) or refused(s), 120) or refused(stamp):
                raise RuntimeError(f"scan {i} not answered in 120 s: {refused(stamp)}")
            latencies["boundary_state"].append(arrival[("hood_decomp/boundary_state", stamp)] - sent[stamp])
            latencies["effects"].append(arrival[("hood_decomp/effects", stamp)] - sent[stamp])
            peer.wait(lambda s=stamp: not np.isnan(node_seconds(s, "hood_decomp_estimator")), 5)
            for node in handler:
                handler[node].append(node_seconds(stamp, f"hood_decomp_{node}"))
            log(f"scan {i}: state {latencies['boundary_state'][-1]:.3f} s (scan node {handler['scan'][-1]:.3f}, "
                f"estimator {handler['estimator'][-1]:.3f}), effects {latencies['effects'][-1]:.3f} s")
            if args.gap_s:
                peer.wait(lambda: False, args.gap_s)
        soak = {}
        if args.soak_seconds:
            rss = []
            start = time.perf_counter()
            count = 0
            while time.perf_counter() - start < args.soak_seconds:
                stamp = 10_000_000_000_000 + 1_000_000_000 * count
                publish(count, stamp)
                count += 1
                peer.wait(lambda: False, max(0.0, start + count - time.perf_counter()))
                rss.append([psutil.Process(p.pid).memory_info().rss / 2**20 for p in processes])
            peer.wait(lambda: all(answered(s) for s in sent if s >= 10_000_000_000_000), 60)
            lost = sum(1 for s in sent if s >= 10_000_000_000_000 and not answered(s))
            rss = np.array(rss)
            tenth = max(1, len(rss) // 10)
            soak = {"seconds": args.soak_seconds, "scans": count, "lost": lost,
                    "rss_mb_first_tenth": rss[:tenth].mean(axis=0).round(1).tolist(),
                    "rss_mb_last_tenth": rss[-tenth:].mean(axis=0).round(1).tolist(),
                    "rss_mb_every_tenth": [rss[i:i + tenth].mean(axis=0).round(1).tolist()
                                           for i in range(0, len(rss), tenth)]}
        best_effort = {}
        if args.best_effort:
            seconds = []
            for i in range(args.best_effort):
                stamp = 30_000_000_000_000 + 1_000_000_000 * i
                cloud = clouds[i % len(clouds)]
                cloud.header.stamp = Time(sec=stamp // 1_000_000_000)
                sent[stamp] = time.perf_counter()
                best_effort_pub.publish(cloud)
                if peer.wait(lambda s=stamp: answered(s) or refused(s), 120) and answered(stamp):
                    seconds.append(arrival[("hood_decomp/boundary_state", stamp)] - sent[stamp])
                log(f"best effort {i + 1}/{args.best_effort}: {'answered' if answered(stamp) else 'LOST'}")
            best_effort = {"sent": args.best_effort, "answered": len(seconds),
                           "state_latency_median_s": statistics.median(seconds) if seconds else None,
                           "state_latency_max_s": max(seconds) if seconds else None}
        inspection = {}
        if args.inspection_parts:
            from bench_inspection import inspect_parts

            seconds, results = inspect_parts(peer, views, args.inspection_parts)
            inspection = {"parts": args.inspection_parts, "points_per_view": args.inspection_points,
                          "latency_s": seconds, "median_s": statistics.median(seconds), "max_s": max(seconds),
                          "results": results}
        oversize = {}
        if args.oversize_points:  # a cloud above the scan node's max_points: refused by name, the next one served
            big = scan_cloud(scans[0].scan, 0)
            big.width = args.oversize_points
            big.row_step = big.point_step * big.width
            big.data = array.array("B", bytes(big.row_step))
            stamp = 20_000_000_000_000
            big.header.stamp = Time(sec=stamp // 1_000_000_000)
            sent_at = time.perf_counter()
            peer.publishers["scan/points"].publish(big)
            peer.wait(lambda: bool(refused(stamp)), 120)
            seconds = time.perf_counter() - sent_at
            publish(0, stamp + 1_000_000_000)
            served = peer.wait(lambda: answered(stamp + 1_000_000_000), 120)
            oversize = {"points": args.oversize_points, "bytes": big.row_step, "refused": refused(stamp),
                        "seconds_to_diagnostic": round(seconds, 2), "next_scan_answered": served}
    finally:
        peer.close()
        stop_nodes(processes)
    # the rest of a scan's latency (transport of the cloud and the field, executor wake-ups) by difference
    latencies["transport"] = [total - a - b for total, a, b in zip(latencies["boundary_state"], handler["scan"],
                                                                    handler["estimator"], strict=True)]
    latencies.update({f"{node} node handler": seconds for node, seconds in handler.items()})
    summary = {key: {"first_s": v[0], "median_s": statistics.median(v), "max_s": max(v)}
               for key, v in latencies.items()}
    print(f"Node latency, {args.resolution} resolution ({len(skin.points):,} skin nodes), {args.points:,}-point "
          f"scans, {platform.machine()}, {psutil.cpu_count()} cores")
    print(f"{'from scan published to':32s} {'first s':>10s} {'median s':>10s} {'max s':>10s}")
    for key, value in summary.items():
        label = key + " received" if key in ("boundary_state", "effects") else "  of which " + key
        print(f"{label:32s} {value['first_s']:10.3f} {value['median_s']:10.3f} {value['max_s']:10.3f}")
    if soak:
        print(f"sustained 1 Hz for {soak['seconds']:.0f} s: {soak['scans']} scans, {soak['lost']} lost; node RSS MB "
              f"(scan, estimator, decomposition) per tenth of the run: {soak['rss_mb_every_tenth']}")
    if best_effort:
        print(f"best-effort publisher: {best_effort['answered']} of {best_effort['sent']} clouds delivered and "
              f"answered; boundary state median {best_effort['state_latency_median_s']} s, max "
              f"{best_effort['state_latency_max_s']} s")
    if inspection:
        print(f"inspection, 4 x {args.inspection_points:,} points, last view -> result: median "
              f"{inspection['median_s']:.3f} s, max {inspection['max_s']:.3f} s over {args.inspection_parts} parts "
              f"({sum(r['success'] for r in inspection['results'])} succeeded)")
    if oversize:
        print(f"oversize cloud of {oversize['points']:,} points ({oversize['bytes'] / 2**20:.0f} MB): "
              f"{oversize['refused'] or 'NOT refused'} after {oversize['seconds_to_diagnostic']} s; next scan "
              f"{'answered' if oversize['next_scan_answered'] else 'NOT answered'}")
    OUT.mkdir(exist_ok=True)
    (OUT / f"bench_nodes_{args.resolution}.json").write_text(json.dumps({
        "benchmark": "nodes", "resolution": args.resolution, "skin_nodes": len(skin.points), "points": args.points,
        "latency": summary, "gap_s": args.gap_s, "soak": soak, "best_effort": best_effort, "inspection": inspection,
        "oversize": oversize,
        "cloud_bytes": len(serialize_message(clouds[0])),
        "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.node()} {platform.machine()}"}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
