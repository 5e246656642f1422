"""Benchmark: the scan step on clouds in scan order and in no spatial order, with and without the tile sort.

A scanner's points follow its lines; a shuffled, voxel-hashed or hash-merged cloud jumps across the part, and every
step that reads the grid and node rows of a point's cell misses the cache (kernels.tile_order). Per size: the field
of bench_scan's cloud as stored (scan order) and shuffled, the shuffled one with the tile sort (the default) and
without it (UNORDERED_STEP_CELLS set to infinity), prepared skin, compiled path, variants interleaved, median wall
time of --repeats. Needs bench_scan's work directory (its bases and clouds):

    scripts/with-env python benchmarks/bench_scan_order.py --work /tmp/bench_scan --resolution paper \
        --sizes 1e6,1e7 --repeats 5

Prints a table and writes benchmarks/out/bench_scan_order.json.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import time

import numpy as np

from hood_decomp.core.scan import kernels, scan_field
from hood_decomp.io.bases import load_bases
from hood_decomp.io.ply import read_scan

OUT = pathlib.Path(__file__).parent / "out"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=pathlib.Path, required=True, help="bench_scan.py's --work directory")
    parser.add_argument("--resolution", default="paper", choices=("default", "paper"))
    parser.add_argument("--sizes", default="1e6,1e7", help="cloud sizes (bench_scan's files cloud_<n>.ply)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    work = args.work / args.resolution
    estimator = scan_field.prepared_estimator(load_bases(work / "bases.h5").skin)
    kernels.load()
    rng = np.random.default_rng(0)
    rows = []
    for size in (int(float(s)) for s in args.sizes.split(",")):
        scanned = np.ascontiguousarray(read_scan(work / f"cloud_{size}.ply").points, dtype=np.float64)
        shuffled = np.ascontiguousarray(scanned[rng.permutation(scanned.shape[0])])
        variants = {"scan order": (scanned, kernels.UNORDERED_STEP_CELLS),
                    "shuffled, tile sort": (shuffled, kernels.UNORDERED_STEP_CELLS),
                    "shuffled, no sort": (shuffled, np.inf)}
        seconds: dict[str, list[float]] = {name: [] for name in variants}
        default = kernels.UNORDERED_STEP_CELLS
        try:
            for repeat in range(args.repeats + 1):  # the first round warms up
                for name, (points, step) in variants.items():
                    kernels.UNORDERED_STEP_CELLS = step
                    start = time.perf_counter()
                    estimator.field(points)
                    if repeat:
                        seconds[name].append(time.perf_counter() - start)
        finally:
            kernels.UNORDERED_STEP_CELLS = default
        medians = {name: statistics.median(v) for name, v in seconds.items()}
        rows.append({"points": size, **{f"{name} s": round(m, 4) for name, m in medians.items()},
                     "seconds": seconds, "load": os.getloadavg()[0]})
        print(f"{args.resolution} {size:>11,} points: " + ", ".join(f"{n} {m:.3f} s" for n, m in medians.items())
              + f" (load {os.getloadavg()[0]:.1f})", flush=True)
    print("\n| points | scan order s | shuffled, tile sort s | shuffled, no sort s | sort's gain |")
    print("|---:|---:|---:|---:|---:|")
    for row in rows:
        print(f"| {row['points']:,} | {row['scan order s']:.3f} | {row['shuffled, tile sort s']:.3f} | "
              f"{row['shuffled, no sort s']:.3f} | {row['shuffled, no sort s'] / row['shuffled, tile sort s']:.2f} x |")
    OUT.mkdir(exist_ok=True)
    (OUT / "bench_scan_order.json").write_text(json.dumps({
        "benchmark": "scan_order", "resolution": args.resolution, "skin_nodes": int(estimator.points_.shape[0]),
        "repeats": args.repeats, "rows": rows, "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} cores"}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
