"""Scenario bags (hood_decomp.ros.scan_bag.write_scenario_bag): what goes in comes out byte for byte, and a bag of
many scans is written as the scans come, in the memory of one (the 1,000-part bag of benchmarks/bench_shift.py)."""

from __future__ import annotations

import tracemalloc
from collections.abc import Iterator

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from hood_decomp.errors import BagError
from hood_decomp.io.bags import read_bag, read_sidecar, typestore
from hood_decomp.ros import scan_bag
from hood_decomp.ros.scan_bag import SCAN_TOPIC, write_scenario_bag
from hood_decomp.synthetic.scanner import ScannerConfig, SyntheticScan
from hood_decomp.synthetic.scenarios import ScenarioScan

START, PERIOD = 1_000_000_000_000, 1_000_000_000


def scenario(index: int, n_points: int) -> ScenarioScan:
    """A scan of ``n_points`` random points (mm) with three reference markers; truth and settings name the index."""
    rng = np.random.default_rng(index)
    pose = np.eye(4)
    pose[:3, 3] = (index, 0.0, 2500.0)
    markers = rng.uniform(-500, 500, (3, 3))
    scan = SyntheticScan(points=rng.uniform(-1000, 1000, (n_points, 3)), scanner_pose=pose, markers=markers,
                         marker_ids=np.array([10 + index, 20, 30]), markers_nominal=markers + 1.0,
                         true_transform=pose, misplacement=np.eye(4), noise_mm=0.02, n_skin_points=n_points,
                         n_outliers=0)
    truth = {"HINGE_Y": 0.1 * index}
    return ScenarioScan(f"part{index}", truth, truth, {}, {}, np.zeros(4), scan, ScannerConfig(n_points=n_points))


def test_scenario_bag_round_trips_bytes_and_points(tmp_path, monkeypatch):
    """Fails if a cloud read back differs by one byte from the serialised message written (captured as rclpy made
    it: a fresh serialisation may differ in its CDR padding bytes, which rclpy leaves uninitialised), if the points
    decoded by rosbags' own CDR decoder (not hood_decomp's) are not the scan's points in metres as float32 with the
    marker centres appended and marked by id, if the stamps are not one period apart, if the sidecar does not state each
    scan in order (name, truth, malformed kind) with the first scan's scanner pose and every scan's markers, or if
    an empty sequence writes a bag without saying so."""
    written: list[bytes] = []

    def serialize(message: object) -> bytes:
        written.append(bytes(serialize_message(message)))
        return written[-1]

    monkeypatch.setattr(scan_bag, "serialize_message", serialize)
    items = [scenario(0, 1000), ("size_mismatch", scenario(1, 1000)), scenario(2, 700)]
    write_scenario_bag(tmp_path / "bag", iter(items), model_id="m", resolution="coarse", description="t")
    records = list(read_bag(tmp_path / "bag"))
    assert [r.topic for r in records] == [SCAN_TOPIC] * 3
    assert [r.timestamp_ns for r in records] == [START, START + PERIOD, START + 2 * PERIOD]
    assert [r.data for r in records] == written
    for record, index in ((records[0], 0), (records[2], 2)):
        scan = items[index].scan
        cloud = typestore().deserialize_cdr(record.data, "sensor_msgs/msg/PointCloud2")
        names = [f.name for f in cloud.fields]
        assert names == ["x", "y", "z", "marker_id"] and all(f.datatype == 7 for f in cloud.fields)  # FLOAT32
        rows = np.frombuffer(cloud.data.tobytes(), dtype=np.float32).reshape(-1, cloud.point_step // 4)
        offsets = [f.offset // 4 for f in cloud.fields]
        expected = np.vstack([scan.points, scan.markers]) / 1000.0
        np.testing.assert_array_equal(rows[:, offsets[:3]], expected.astype(np.float32))
        np.testing.assert_array_equal(rows[:, offsets[3]], np.r_[np.full(len(scan.points), -1.0),
                                                                 scan.marker_ids].astype(np.float32))
        assert cloud.header.frame_id == "scanner" and cloud.header.stamp.sec == record.timestamp_ns // 10**9
    broken = typestore().deserialize_cdr(records[1].data, "sensor_msgs/msg/PointCloud2")
    assert broken.data.size != broken.row_step * broken.height  # the malformed cloud is written as made
    sidecar = read_sidecar(tmp_path / "bag")
    assert [s["name"] for s in sidecar["scans"]] == ["part0", "part1", "part2"]
    assert [s["kind"] for s in sidecar["scans"]] == ["good", "size_mismatch", "good"]
    assert [s["truth_mm"]["HINGE_Y"] for s in sidecar["scans"]] == [0.0, 0.1, 0.2]
    assert [s["points"] for s in sidecar["scans"]] == [1003, broken.width, 703]
    assert sidecar["scanner_pose_mm"] == items[0].scan.scanner_pose.tolist()
    assert sorted(sidecar["marker_positions_mm"], key=int) == ["10", "11", "12", "20", "30"]
    np.testing.assert_array_equal(sidecar["marker_positions_mm"]["12"], items[2].scan.markers_nominal[0])
    with pytest.raises(BagError, match="no scans"):
        write_scenario_bag(tmp_path / "empty", iter([]), model_id="m", resolution="coarse", description="t")


def _peak_writing(path, n_scans: int, n_points: int) -> int:
    """Peak traced Python memory (bytes) while writing ``n_scans`` scans made one at a time by a generator."""

    def scans() -> Iterator[ScenarioScan]:
        for i in range(n_scans):
            yield scenario(i, n_points)

    tracemalloc.start()
    try:
        write_scenario_bag(path, scans(), model_id="m", resolution="coarse", description="t")
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_scenario_bag_memory_flat_in_the_number_of_scans(tmp_path):
    """Fails if write_scenario_bag holds the scans or their messages until the end (or the MCAP writer buffers the
    bag): writing 16 scans of 100,000 points (1.6 MB each as a cloud, 2.4 MB as points) then peaks at ~3x
    writing 2 instead of the same. Measured with tracemalloc, which sees numpy's and the serialised bytes'
    allocations."""
    n_points = 100_000
    _peak_writing(tmp_path / "warm-up", 1, 1000)  # the typestore and rclpy's type support are made once
    two = _peak_writing(tmp_path / "two", 2, n_points)
    sixteen = _peak_writing(tmp_path / "sixteen", 16, n_points)
    message = 16 * n_points
    assert sum(1 for _ in read_bag(tmp_path / "sixteen")) == 16
    assert sixteen < two + 2 * message, (two / 1e6, sixteen / 1e6)  # holding them: 2.8x two (34 vs 12 MB)
    assert sixteen < 12 * message, sixteen / 1e6  # one scan's copies in flight (~10 MB), never the 16 clouds' 26 MB
