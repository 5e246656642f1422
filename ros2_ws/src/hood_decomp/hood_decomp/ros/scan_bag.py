"""Scans as a cell's scanner would send them (sensor_msgs/PointCloud2 in metres, scanner frame) and scenario bags,
among them a multi-view part with the robot's poses on /tf and scan/pose (:func:`write_multiview_bag`).

A cloud carries x, y, z (float32) and ``marker_id`` (float32): -1 for surface points, the marker's id for the reference
marker centres the scanner software reports, appended at the end. The sidecar of each bag states the truth of every
scan (see :func:`write_scenario_bag`).
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from rclpy.serialization import serialize_message
from std_msgs.msg import Header

from hood_decomp.errors import BagError
from hood_decomp.io.bags import BagWriter, Record, write_bag, write_sidecar
from hood_decomp.ros import messages
from hood_decomp.synthetic.scanner import SyntheticScan
from hood_decomp.synthetic.scenarios import ScenarioScan

SCAN_TOPIC = "scan/points"
POSE_TOPIC = "scan/pose"
SCANNER_FRAME = "scanner"
MARKER_FIELD = "marker_id"
#: frames of a multi-view bag's robot: part <- robot base (static), base <- flange (the robot), flange <- scanner
#: (static hand-eye calibration)
PART_FRAME, BASE_FRAME, FLANGE_FRAME = "hood", "robot_base", "flange"

# Malformed clouds a bag may mix in, and what is wrong with each (the node must name it on /diagnostics).
MALFORMED = {
    "no_xyz": "a cloud without x/y/z fields",
    "size_mismatch": "data length != row_step * height",
    "int16_x": "x of unsupported datatype INT16",
    "empty": "a cloud with no points",
    "all_nan": "every point NaN",
    "metres_as_mm": "coordinates a thousand times too small (a cloud in mm sent as if in m)",
}


def scan_cloud(scan: SyntheticScan, stamp_ns: int) -> Any:
    """The scan's points and marker centres as one PointCloud2 in metres, scanner frame."""
    points = np.vstack([scan.points, scan.markers])
    ids = np.concatenate([np.full(len(scan.points), -1.0), scan.marker_ids.astype(float)])
    return messages.points_to_cloud(points, _header(stamp_ns), channels={MARKER_FIELD: ids})


def malformed_cloud(kind: str, scan: SyntheticScan, stamp_ns: int, n_points: int = 5000) -> Any:
    """A cloud of (at most) ``n_points`` of the scan that is wrong in the way ``kind`` (a key of MALFORMED) says."""
    points = scan.points[:: max(1, len(scan.points) // n_points)]
    if kind == "empty":
        return messages.points_to_cloud(np.zeros((0, 3)), _header(stamp_ns))
    if kind == "all_nan":
        return messages.points_to_cloud(np.full((n_points, 3), np.nan), _header(stamp_ns))
    if kind == "metres_as_mm":  # converted to metres once too often
        return messages.points_to_cloud(points * messages.M_PER_MM, _header(stamp_ns))
    cloud = messages.points_to_cloud(points, _header(stamp_ns))
    if kind == "no_xyz":
        for field in cloud.fields:
            field.name = {"x": "a", "y": "b", "z": "c"}.get(field.name, field.name)
    elif kind == "size_mismatch":
        cloud.data = cloud.data[: len(cloud.data) - 7]
    elif kind == "int16_x":
        cloud.fields[0].datatype = 3
    else:
        raise ValueError(f"unknown malformed kind {kind!r}; expected one of {sorted(MALFORMED)}")
    return cloud


def _header(stamp_ns: int) -> Header:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return Header(frame_id=SCANNER_FRAME, stamp=Time(sec=sec, nanosec=nanosec))


def write_scenario_bag(path: str | pathlib.Path, items: Iterable[ScenarioScan | tuple[str, ScenarioScan]],
                       *, model_id: str, resolution: str, description: str, start_ns: int = 1_000_000_000_000,
                       period_ns: int = 1_000_000_000) -> pathlib.Path:
    """Write a bag of scans (one per second of bag time) and its sidecar ``<path>.json``.

    items: a ScenarioScan (a good scan), or (malformed kind, ScenarioScan) for a broken cloud built from that scan.
    They are consumed one at a time and each cloud is written as it comes (rosbags' MCAP writer flushes a chunk per
    MiB), so a generator of 1,000 500k-point scans needs the memory of one scan: only the sidecar's entries are kept.
    The sidecar lists, per scan in order: stamp, kind ("good" or the malformed kind and what is wrong), the settings,
    the truth of the declared parameters (mm), lifted buffers, undeclared effects, scan noise; plus the nominal
    scanner pose (the first scan's) and marker positions (the cell calibration the scan node needs) and the model it
    belongs to. BagError when ``items`` is empty (the bag directory is then left without a scan).
    """
    entries: list[dict[str, Any]] = []
    markers: dict[str, list[float]] = {}
    scanner_pose: list[list[float]] | None = None
    with BagWriter(path) as bag:
        for index, item in enumerate(items):
            stamp = start_ns + index * period_ns
            kind, scenario = item if isinstance(item, tuple) else ("good", item)
            scan = scenario.scan
            cloud = scan_cloud(scan, stamp) if kind == "good" else malformed_cloud(kind, scan, stamp)
            bag.write(Record(SCAN_TOPIC, "sensor_msgs/msg/PointCloud2", stamp, bytes(serialize_message(cloud))))
            sec, nanosec = divmod(stamp, 1_000_000_000)
            entries.append({
                "stamp": f"{sec}.{nanosec:09d}", "kind": kind, "problem": MALFORMED.get(kind), "name": scenario.name,
                "settings_mm": scenario.settings, "truth_mm": scenario.truth_mm, "lifted": scenario.lifted,
                "undeclared_mm": scenario.undeclared_mm, "noise_mm": scenario.config.noise_mm,
                "points": int(cloud.width * cloud.height),
            })
            if scanner_pose is None:
                scanner_pose = scan.scanner_pose.tolist()
            markers.update({str(int(i)): p.tolist() for i, p in zip(scan.marker_ids, scan.markers_nominal,
                                                                     strict=True)})
    if scanner_pose is None:
        raise BagError(f"bag {path}: no scans to write")
    return write_sidecar(path, {
        "description": description, "model": {"preset": "hood", "resolution": resolution, "model_id": model_id},
        "topic": SCAN_TOPIC, "frame_id": SCANNER_FRAME, "marker_field": MARKER_FIELD,
        "scanner_pose_mm": scanner_pose,
        "marker_positions_mm": dict(sorted(markers.items(), key=lambda kv: int(kv[0]))),
        "scans": entries,
    })


def write_node_params(path: str | pathlib.Path, sidecar: dict[str, Any],
                      decomposition_pair_timeout_s: float = 2.0) -> pathlib.Path:
    """A ROS parameter file (--params-file) with the cell calibration a bag's sidecar states, in ROS units (metres):
    the scan node's nominal scanner pose and reference-marker positions."""
    pose, markers = messages.calibration_to_params(sidecar["scanner_pose_mm"], sidecar["marker_positions_mm"])
    path = pathlib.Path(path)
    path.write_text(
        "hood_decomp_scan:\n  ros__parameters:\n"
        f"    scanner_pose: {json.dumps(pose)}\n"
        f"    marker_positions: {json.dumps(markers)}\n"
        f"    marker_field: {MARKER_FIELD}\n"
        "hood_decomp_decomposition:\n  ros__parameters:\n"
        f"    pair_timeout_s: {float(decomposition_pair_timeout_s)}\n"
    )
    return path


def transform_stamped(parent: str, child: str, pose_mm: np.ndarray, stamp_ns: int) -> Any:
    """geometry_msgs/TransformStamped (metres) of a (4, 4) transform parent <- child in mm."""
    from geometry_msgs.msg import TransformStamped

    from hood_decomp.ros.poses import matrix_quaternion

    item = TransformStamped()
    item.header = _header(stamp_ns)
    item.header.frame_id, item.child_frame_id = parent, child
    t, r = item.transform.translation, item.transform.rotation
    t.x, t.y, t.z = (float(v) for v in np.asarray(pose_mm)[:3, 3] * messages.M_PER_MM)
    r.x, r.y, r.z, r.w = (float(v) for v in matrix_quaternion(np.asarray(pose_mm)[:3, :3]))
    return item


def write_multiview_bag(path: str | pathlib.Path, views: Sequence[ScenarioScan], robot_poses_mm: Sequence[np.ndarray],
                        *, part_id: str, model_id: str, resolution: str, description: str,
                        base_pose_mm: np.ndarray, hand_eye_mm: np.ndarray, start_ns: int = 1_000_000_000_000,
                        period_ns: int = 2_000_000_000) -> pathlib.Path:
    """A bag of one part seen in several views from a robot, and its sidecar ``<path>.json``.

    views: the part's scans (one state, different scanner poses); robot_poses_mm: per view the pose the robot reports
    for the scanner (part <- scanner, mm; the truth is each scan's ``true_transform``). Recorded: ``/tf_static`` once
    (part <- robot base ``base_pose_mm``, flange <- scanner ``hand_eye_mm``), then per view ``/tf`` (base <- flange,
    the robot standing still for the view: at the cloud stamp -/+ 20 ms), ``scan/pose`` (part <- scanner at the cloud
    stamp, the same robot pose) and the cloud (frame ``scanner``, with its marker centres). The sidecar states the
    truth, the robot's pose error per view, and what an inspection of the part expects.
    """
    from tf2_msgs.msg import TFMessage

    records: list[Record] = []

    def record(topic: str, msgtype: str, stamp: int, message: Any) -> None:
        records.append(Record(topic, msgtype, stamp, bytes(serialize_message(message))))

    record("/tf_static", "tf2_msgs/msg/TFMessage", start_ns - period_ns, TFMessage(transforms=[
        transform_stamped(PART_FRAME, BASE_FRAME, base_pose_mm, start_ns - period_ns),
        transform_stamped(FLANGE_FRAME, SCANNER_FRAME, hand_eye_mm, start_ns - period_ns)]))
    entries = []
    to_base, from_hand = np.linalg.inv(base_pose_mm), np.linalg.inv(hand_eye_mm)
    for index, (view, robot) in enumerate(zip(views, robot_poses_mm, strict=True)):
        stamp = start_ns + index * period_ns
        flange = to_base @ robot @ from_hand  # base <- flange that puts the scanner at the robot's pose
        for offset in (-20_000_000, 20_000_000):
            record("/tf", "tf2_msgs/msg/TFMessage", stamp + offset, TFMessage(transforms=[
                transform_stamped(BASE_FRAME, FLANGE_FRAME, flange, stamp + offset)]))
        record(POSE_TOPIC, "geometry_msgs/msg/TransformStamped", stamp,
               transform_stamped(PART_FRAME, SCANNER_FRAME, robot, stamp))
        record(SCAN_TOPIC, "sensor_msgs/msg/PointCloud2", stamp, scan_cloud(view.scan, stamp))
        error = robot @ np.linalg.inv(view.scan.true_transform)
        sec, nanosec = divmod(stamp, 1_000_000_000)
        entries.append({
            "stamp": f"{sec}.{nanosec:09d}", "name": view.name, "points": len(view.scan.points),
            "markers": len(view.scan.markers), "noise_mm": view.config.noise_mm,
            "view_center": list(view.config.view_center), "view_tilt_deg": list(view.config.view_tilt_deg),
            "fov_deg": view.config.fov_deg, "true_pose_mm": view.scan.true_transform.tolist(),
            "robot_pose_mm": np.asarray(robot).tolist(),
            "robot_pose_error_mm": float(np.linalg.norm(error[:3, 3])),
            "robot_pose_error_deg": float(np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))),
        })
    write_bag(path, sorted(records, key=lambda r: r.timestamp_ns))
    first = views[0]
    markers = {str(int(i)): p.tolist() for view in views
               for i, p in zip(view.scan.marker_ids, view.scan.markers_nominal, strict=True)}
    return write_sidecar(path, {
        "description": description, "model": {"preset": "hood", "resolution": resolution, "model_id": model_id},
        "kind": "multi-view part", "part_id": part_id, "expected_views": len(views),
        "topic": SCAN_TOPIC, "pose_topic": POSE_TOPIC, "frame_id": SCANNER_FRAME, "part_frame": PART_FRAME,
        "tf_frames": [PART_FRAME, BASE_FRAME, FLANGE_FRAME, SCANNER_FRAME], "marker_field": MARKER_FIELD,
        "marker_positions_mm": dict(sorted(markers.items(), key=lambda kv: int(kv[0]))),
        "settings_mm": first.settings, "truth_mm": first.truth_mm, "lifted": first.lifted,
        "undeclared_mm": first.undeclared_mm, "views": entries,
    })
