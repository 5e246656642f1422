"""Scan node: scan/points (sensor_msgs/PointCloud2, metres, scanner frame) -> hood_decomp/displacement and
hood_decomp/displacement_cloud (the skin with a normal-displacement channel, metres, for RViz).

The cloud is read with one buffer copy (hood_decomp.ros.messages / pointcloud), registered to the nominal part and
turned into one signed normal displacement per visible skin node (hood_decomp.core.scan.scan_field). Clouds larger
than ``max_points`` are refused before any copy.
"""

from __future__ import annotations

import numpy as np
from hood_decomp_msgs.msg import DisplacementField
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

from hood_decomp.errors import ScanError
from hood_decomp.ros import messages
from hood_decomp.ros.node_common import HoodNode, declare, spin


class ScanNode(HoodNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_scan")
        self.part_frame = declare(self, "part_frame", "hood", "frame_id of the published fields (the part frame)")
        pose = declare(self, "scanner_pose", [float(v) for v in np.eye(4).ravel()],
                       "scanner-to-part transform, 16 numbers row-major, translation in metres (cell calibration)")
        markers = self.declare_parameter("marker_positions", Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            description="nominal reference-marker centres in the part frame: id, x, y, z (metres) per marker; the "
            "cloud reports measured centres as points whose marker_field is the id (-1 for surface points)")).value
        self.marker_field = declare(self, "marker_field", "marker_id", "per-point field holding marker ids")
        self.max_points = declare(self, "max_points", 5_000_000, "largest cloud accepted (points)", 1, 100_000_000)
        self.min_coverage = declare(self, "min_coverage", 0.2, "smallest seen fraction of the skin", 0.0, 1.0)
        self.scanner_pose, self.markers_nominal = messages.calibration_from_params(pose, markers or [])
        self.estimator = self.skin_clouds = None
        if self.bases is not None:  # one-time preparation of the skin: the scan-field estimator and the cloud's xyz
            from hood_decomp.core.scan.scan_field import prepared_estimator, warm_up

            self.estimator = prepared_estimator(self.bases.skin)
            warm_up(self.estimator)  # the first scan then runs at steady-state speed (issue 19)
            self.skin_clouds = messages.SkinClouds(self.bases.skin)
        self.field_pub = self.publisher(DisplacementField, "hood_decomp/displacement")
        self.cloud_pub = self.publisher(PointCloud2, "hood_decomp/displacement_cloud")
        self.subscription(PointCloud2, "scan/points", self.guarded("scan", self.on_cloud))

    def on_cloud(self, msg: PointCloud2) -> dict[str, object]:
        from hood_decomp.core.scan.scan_field import field_from_scan

        bases = self.require_bases()
        n_points = int(msg.width) * int(msg.height)
        if n_points > self.max_points:
            raise ScanError(f"cloud has {n_points:,} points; this node accepts at most {self.max_points:,} "
                            "(parameter max_points)")
        points_mm, markers_mm, markers_nominal_mm = messages.scan_to_mm(msg, self.marker_field, self.markers_nominal)
        field, registration = field_from_scan(bases.skin, points_mm, scanner_pose=self.scanner_pose,
                                              markers_mm=markers_mm, markers_nominal_mm=markers_nominal_mm,
                                              min_coverage=self.min_coverage, estimator=self.estimator)
        header = msg.header
        header.frame_id = self.part_frame
        self.field_pub.publish(messages.field_to_msg(field, header))
        self.cloud_pub.publish(self.skin_clouds.displacement(field, header))
        return {"points": points_mm.shape[0], "markers": 0 if markers_mm is None else len(markers_mm),
                "coverage": f"{field.coverage:.3f}",
                "noise_rms_mm": f"{field.noise_rms:.4f}", "registration": registration.method,
                "overlap": f"{registration.overlap:.3f}"}


def main(args: list[str] | None = None) -> int:
    return spin(ScanNode, args)
