"""Scan node: scan/points (sensor_msgs/PointCloud2, metres, scanner frame) -> hood_decomp/displacement and
hood_decomp/displacement_cloud (the skin with a normal-displacement channel, metres, for RViz).

The cloud is read with one buffer copy (hood_decomp.ros.messages / pointcloud), registered to the nominal part and
turned into one signed normal displacement per visible skin node (hood_decomp.core.scan.scan_field). Clouds larger
than ``max_points`` are refused before any copy. Reliable and best-effort scanner drivers both connect (a reliable
and a best-effort subscription, each cloud taken once); the field is published transient-local (the latest result).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from hood_decomp_msgs.msg import DisplacementField
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

from hood_decomp.errors import ScanError
from hood_decomp.ros import messages
from hood_decomp.ros.node_common import HoodNode, declare, declare_list, spin


class ScanNode(HoodNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_scan")
        declare(self, "part_frame", "hood", "frame_id of the published fields (the part frame)")
        declare(self, "scanner_pose", [float(v) for v in np.eye(4).ravel()],
                "scanner-to-part transform, 16 numbers row-major, translation in metres (cell calibration)")
        declare_list(self, "marker_positions", Parameter.Type.DOUBLE_ARRAY, "nominal reference-marker centres in "
                     "the part frame: id, x, y, z (metres) per marker; the cloud reports measured centres as points "
                     "whose marker_field is the id (-1 for surface points)")
        declare(self, "marker_field", "marker_id", "per-point field holding marker ids")
        declare(self, "max_points", 5_000_000, "largest cloud accepted (points)", 1, 100_000_000)
        declare(self, "min_coverage", 0.2, "smallest seen fraction of the skin", 0.0, 1.0)
        self.prepared: dict[str, tuple[Any, messages.SkinClouds]] = {}  # model_id -> (estimator, skin clouds)
        self.field_pub = self.cloud_pub = None

    def check_parameter(self, parameter: Parameter) -> str:
        if parameter.name not in ("scanner_pose", "marker_positions") or parameter.value is None:
            return super().check_parameter(parameter)
        values = np.asarray(parameter.value, dtype=float)
        if parameter.name == "scanner_pose" and (values.shape != (16,) or not np.isfinite(values).all()):
            return f"16 finite numbers (row-major 4 x 4), got {values.size}"
        if parameter.name == "marker_positions" and (values.size % 4 or not np.isfinite(values).all()):
            return f"id, x, y, z per marker (a multiple of 4 finite numbers), got {values.size}"
        return ""

    def configure_node(self) -> None:
        from hood_decomp.core.scan.scan_field import prepared_estimator

        # one-time preparation of each variant's skin: the scan-field estimator and the cloud's xyz
        self.prepared = {bases.model_id: (prepared_estimator(bases.skin), messages.SkinClouds(bases.skin))
                         for bases in self.variant_bases.values()}
        self.field_pub = self.publisher(DisplacementField, "hood_decomp/displacement", latest=True)
        self.cloud_pub = self.publisher(PointCloud2, "hood_decomp/displacement_cloud")

    def activate_node(self) -> None:
        # reliable and best-effort scanner drivers both connect; each cloud is taken once
        self.subscription(PointCloud2, "scan/points", self.guarded("scan", self.on_cloud), any_reliability=True)

    def on_cloud(self, msg: PointCloud2) -> dict[str, object]:
        from hood_decomp.core.scan.scan_field import field_from_scan

        bases = self.require_bases()  # a lone cloud is of the default variant; an inspection names its own
        estimator, skin_clouds = self.prepared[bases.model_id]
        n_points = int(msg.width) * int(msg.height)
        max_points = self.param("max_points")
        if n_points > max_points:
            raise ScanError(f"cloud has {n_points:,} points; this node accepts at most {max_points:,} "
                            "(parameter max_points)")
        scanner_pose, markers_nominal = messages.calibration_from_params(self.param("scanner_pose"),
                                                                         self.param("marker_positions"))
        points_mm, markers_mm, markers_nominal_mm = messages.scan_to_mm(msg, self.param("marker_field"),
                                                                        markers_nominal)
        field, registration = field_from_scan(bases.skin, points_mm, scanner_pose=scanner_pose,
                                              markers_mm=markers_mm, markers_nominal_mm=markers_nominal_mm,
                                              min_coverage=self.param("min_coverage"), estimator=estimator)
        header = msg.header
        part_id = messages.part_id_of(msg)  # a cloud names no part: one id per stamp (an inspection names its own)
        header.frame_id = self.param("part_frame")
        self.field_pub.publish(messages.field_to_msg(field, header, part_id))
        self.cloud_pub.publish(skin_clouds.displacement(field, header))
        return {"part_id": part_id, "points": points_mm.shape[0],
                "markers": 0 if markers_mm is None else len(markers_mm), "coverage": f"{field.coverage:.3f}",
                "noise_rms_mm": f"{field.noise_rms:.4f}", "registration": registration.method,
                "overlap": f"{registration.overlap:.3f}"}


def main(args: list[str] | None = None) -> int:
    return spin(ScanNode, args)
