"""Benchmark: a 1,000,000-point PointCloud2 to an (N, 3) array and back (issue 2; target < 30 ms each way).

Compared side by side with a per-point Python conversion (struct per point), because sensor_msgs_py is not on PyPI
for the wheel-based install, and (issue 19; target: the read within 1.5 x) with a plain numpy structured view that
copies x, y, z to float64 and scales them, without any check; also a cloud with 0.2 % NaN points (dropped).
Run: scripts/with-env python benchmarks/bench_pointcloud.py [--points N]
Prints a table and writes benchmarks/out/bench_pointcloud.json.
"""

from __future__ import annotations

import argparse
import array
import json
import os
import pathlib
import platform
import struct
import time

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from hood_decomp.ros.pointcloud import cloud_to_xyz, xyz_to_cloud

OUT = pathlib.Path(__file__).parent / "out"


def best_of(function, repeats: int) -> float:
    """Best wall time of ``repeats`` calls, seconds (the least disturbed run on a shared machine)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def scanner_cloud(points: np.ndarray) -> PointCloud2:
    """A typical scanner layout: float32 x, y, z, float32 intensity, 4 bytes padding (point_step 20)."""
    n = points.shape[0]
    record = np.zeros(n, dtype=np.dtype({"names": ["x", "y", "z", "i"], "formats": ["<f4"] * 4,
                                         "offsets": [0, 4, 8, 12], "itemsize": 20}))
    record["x"], record["y"], record["z"], record["i"] = points[:, 0], points[:, 1], points[:, 2], 1.0
    cloud = PointCloud2(header=Header(frame_id="scanner"), height=1, width=n, is_bigendian=False, point_step=20,
                        row_step=20 * n, is_dense=True)
    cloud.fields = [PointField(name=c, offset=4 * k, datatype=7, count=1) for k, c in enumerate("xyzi")]
    cloud.data = array.array("B", record.tobytes())
    return cloud


def per_point_read(cloud: PointCloud2) -> np.ndarray:
    raw = bytes(cloud.data)
    unpack = struct.Struct("<fff").unpack_from
    return np.array([unpack(raw, i * cloud.point_step) for i in range(cloud.width * cloud.height)])


def plain_view_read(cloud: PointCloud2) -> np.ndarray:
    """The floor: one structured view, x, y, z copied to float64 and scaled; no validation, no NaN test."""
    view = np.frombuffer(cloud.data, dtype=np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3,
                                                     "offsets": [0, 4, 8], "itemsize": cloud.point_step}))
    out = np.empty((view.size, 3))
    out[:, 0], out[:, 1], out[:, 2] = view["x"], view["y"], view["z"]
    out *= 1000.0
    return out


def median_of(function, repeats: int) -> float:
    """Median wall time of ``repeats`` calls, seconds."""
    return float(np.median([best_of(function, 1) for _ in range(repeats)]))


def per_point_write(points: np.ndarray) -> PointCloud2:
    buffer = bytearray(12 * points.shape[0])
    pack = struct.Struct("<fff").pack_into
    for i, (x, y, z) in enumerate(points.tolist()):
        pack(buffer, 12 * i, x, y, z)
    cloud = PointCloud2(height=1, width=points.shape[0], point_step=12, row_step=len(buffer))
    cloud.data = array.array("B", buffer)
    return cloud


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.0, 1.0, (args.points, 3)).astype(np.float32).astype(np.float64)
    cloud = scanner_cloud(points)
    assert np.array_equal(cloud_to_xyz(cloud), points)
    holes = points.copy()
    holes[::500] = np.nan
    holes = scanner_cloud(holes)

    rows = {
        "read (cloud -> array), hood_decomp": best_of(lambda: cloud_to_xyz(cloud, scale=1000.0), args.repeats),
        "write (array -> cloud), hood_decomp": best_of(lambda: xyz_to_cloud(points, Header(), scale=0.001),
                                                       args.repeats),
        "read (cloud -> array), plain numpy view": best_of(lambda: plain_view_read(cloud), args.repeats),
        "read median of 21, hood_decomp": median_of(lambda: cloud_to_xyz(cloud, scale=1000.0), 21),
        "read median of 21, plain numpy view": median_of(lambda: plain_view_read(cloud), 21),
        "read 0.2 % NaN dropped, median of 21, hood_decomp": median_of(lambda: cloud_to_xyz(holes, scale=1000.0), 21),
        "read (cloud -> array), per-point Python": best_of(lambda: per_point_read(cloud), 1),
        "write (array -> cloud), per-point Python": best_of(lambda: per_point_write(points), 1),
    }
    print(f"PointCloud2 conversion, {args.points:,} points ({platform.processor() or platform.machine()}, "
          f"best of {args.repeats} for hood_decomp, 1 run per-point)")
    print(f"{'conversion':45s} {'ms':>10s}")
    for name, seconds in rows.items():
        print(f"{name:45s} {1000 * seconds:10.1f}")
    OUT.mkdir(exist_ok=True)
    result = {"benchmark": "pointcloud", "points": args.points, "target_ms": 30.0, "load_average": os.getloadavg(),
              "ms": {name: round(1000 * seconds, 2) for name, seconds in rows.items()},
              "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.node()} {platform.machine()}"}
    (OUT / "bench_pointcloud.json").write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
