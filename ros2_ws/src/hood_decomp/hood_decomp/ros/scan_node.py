"""Scan node: scan/points (sensor_msgs/PointCloud2, metres, scanner frame) -> hood_decomp/displacement and
hood_decomp/displacement_cloud (the skin with a normal-displacement channel, metres, for RViz).

The cloud is read with one buffer copy (hood_decomp.ros.messages / pointcloud), placed by its pose (TF, scan/pose,
the scanner_pose parameter: hood_decomp.ros.poses; markers refine it), registered to the nominal part and turned into
one signed normal displacement per visible skin node (hood_decomp.core.scan.scan_field). Clouds larger than
``max_points`` are refused before any copy. While an InspectPart goal is open, clouds are the views of its part
(hood_decomp.ros.inspection), with the bases of the goal's variant; otherwise one cloud gives one field of the default
bases. Reliable and best-effort scanner drivers both connect (a reliable and a best-effort subscription, each cloud
taken once); the field is published transient-local (the latest result).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from hood_decomp_msgs.msg import DisplacementField
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from hood_decomp.core.scan.fusion import ScanView
from hood_decomp.core.scan.registration import MarkerNoiseHistory
from hood_decomp.core.types import DisplacementField as CoreField
from hood_decomp.errors import ScanError
from hood_decomp.ros import messages
from hood_decomp.ros.inspection import InspectionServer
from hood_decomp.ros.node_common import HoodNode, declare, declare_list, spin, through_middleware
from hood_decomp.ros.poses import PoseSources, PoseTopic, tf_lookup

#: points of the warm-up scan at configure: a cell's scan size (bench_nodes' 1M-point clouds)
WARM_UP_POINTS = 1_000_000


class ScanNode(HoodNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_scan")
        declare(self, "part_frame", "hood", "frame_id of the published fields (the part frame)")
        declare(self, "scanner_pose", [float(v) for v in np.eye(4).ravel()],
                "scanner-to-part transform, 16 numbers row-major, translation in metres (cell calibration); the "
                "identity means unset: a lone cloud without TF or scan/pose is then in the part frame")
        declare_list(self, "marker_positions", Parameter.Type.DOUBLE_ARRAY, "nominal reference-marker centres in "
                     "the part frame: id, x, y, z (metres) per marker; the cloud reports measured centres as points "
                     "whose marker_field is the id (-1 for surface points)")
        declare(self, "marker_field", "marker_id", "per-point field holding marker ids")
        declare(self, "marker_std_mm", 0.0, "the scanner's calibrated marker-centre noise, mm per coordinate, for "
                "the marker registration's pose covariance; 0: not stated, estimated from each cloud's marker "
                "residual. A stated value the marker residuals reject (chi-square, 3K - 6 dof per cloud, two-sided "
                "0.1 %; the cloud alone and pooled over the last 20 clouds under the same value) is replaced by the "
                "estimate and reported as a WARN on /diagnostics", 0.0, 10.0)
        declare(self, "max_points", 5_000_000, "largest cloud accepted (points)", 1, 100_000_000)
        declare(self, "min_coverage", 0.2, "smallest seen fraction of the skin", 0.0, 1.0)
        use_tf = declare(self, "use_tf", True, "take each cloud's pose from TF (part_frame <- the cloud's frame at "
                         "its stamp) before scan/pose and scanner_pose; read at start")
        declare(self, "tf_max_extrapolation_s", 0.0, "how far past the newest transform a TF lookup may reach (s; "
                "0: none, as tf2); read at start", 0.0, 10.0)
        declare(self, "pose_wait_s", 0.5, "how long a cloud waits for its transform or scan/pose message still on "
                "its way (s); read at start", 0.0, 10.0)
        declare(self, "inspection_timeout_s", 120.0, "an inspection's timeout when its goal states none (s)",
                0.1, 86400.0)
        declare(self, "result_timeout_s", 30.0, "how long an inspection waits for the estimator's answer to its "
                "fused field (s)", 0.1, 3600.0)
        self.prepared: dict[str, tuple[Any, messages.SkinClouds]] = {}  # model_id -> (estimator, skin clouds)
        self.marker_history = MarkerNoiseHistory()
        self.field_pub = self.cloud_pub = None
        # pose sources listen from the start (TF arrives before the first cloud), in the order of the module docstring
        wait_s = self.param("pose_wait_s")
        sources = [("scan/pose", PoseTopic(self, wait_s=wait_s).lookup)]
        if use_tf:
            try:
                tf, name = tf_lookup(self, max_extrapolation_s=self.param("tf_max_extrapolation_s"), wait_s=wait_s)
                sources.insert(0, (name, tf.lookup))
            except ImportError as error:  # neither tf2_ros nor the workspace's tf2_msgs: say so, serve without TF
                self.get_logger().error(f"no TF: {error} (build ros2_ws/src/tf2_msgs or install tf2_ros)")
        self.poses = PoseSources(sources)
        self.inspection = InspectionServer(self, bases_and_estimator=self.bases_and_estimator,
                                           marker_statement=self.marker_statement,
                                           publish_field=self.publish_field, parameter=self.param,
                                           serving=lambda: self.state == "active")

    def check_parameter(self, parameter: Parameter) -> str:
        if parameter.name == "marker_std_mm" and not (isinstance(parameter.value, float)
                                                      and 0.0 <= parameter.value <= 10.0):
            return f"a number of mm in [0, 10] (0: not stated), got {parameter.value!r}"
        if parameter.name not in ("scanner_pose", "marker_positions") or parameter.value is None:
            return super().check_parameter(parameter)
        values = np.asarray(parameter.value, dtype=float)
        if parameter.name == "scanner_pose" and (values.shape != (16,) or not np.isfinite(values).all()):
            return f"16 finite numbers (row-major 4 x 4), got {values.size}"
        if parameter.name == "marker_positions" and (values.size % 4 or not np.isfinite(values).all()):
            return f"id, x, y, z per marker (a multiple of 4 finite numbers), got {values.size}"
        return ""

    def configure_node(self) -> None:
        from hood_decomp.core.scan.scan_field import prepared_estimator, warm_up

        # one-time preparation of each variant's skin: the scan-field estimator and the cloud's xyz
        self.prepared = {bases.model_id: (prepared_estimator(bases.skin), messages.SkinClouds(bases.skin))
                         for bases in self.variant_bases.values()}
        header = Header(frame_id=self.param("part_frame"))
        for estimator, clouds in self.prepared.values():
            field = warm_up(estimator, WARM_UP_POINTS)  # the first scan then runs at steady-state speed (issue 19)
            # and so do the node's own conversions: a scan-sized cloud in (as the middleware hands it over), a field
            # and its displacement cloud out (nothing published)
            cloud = messages.points_to_cloud(np.resize(estimator.points_, (WARM_UP_POINTS, 3)), header)
            messages.scan_to_mm(through_middleware(cloud), self.param("marker_field"), {})
            through_middleware(messages.field_to_msg(field, header, "warm-up"))
            clouds.displacement(field, header)
        self.field_pub = self.publisher(DisplacementField, "hood_decomp/displacement", latest=True)
        self.cloud_pub = self.publisher(PointCloud2, "hood_decomp/displacement_cloud")

    def activate_node(self) -> None:
        # reliable and best-effort scanner drivers both connect; each cloud is taken once
        self.subscription(PointCloud2, "scan/points", self.guarded("scan", self.on_cloud), any_reliability=True)

    def marker_statement(self, markers_mm: Any, markers_nominal_mm: Any) -> tuple[float | None, Any]:
        """The marker noise to register a cloud with and the check of the stated one over this scanner's recent
        clouds (parameter marker_std_mm, 0: not stated; core.scan.registration.MarkerNoiseHistory)."""
        return self.marker_history.statement(float(self.param("marker_std_mm")) or None, markers_mm,
                                             markers_nominal_mm)

    def bases_and_estimator(self, variant: str) -> tuple[Any, Any]:
        """The bases and the prepared scan-field estimator of a part variant ("" = the default bases)."""
        bases = self.bases_for_variant(variant)
        return bases, self.prepared[bases.model_id][0]

    def on_cloud(self, msg: PointCloud2) -> dict[str, object]:
        from hood_decomp.core.scan.scan_field import field_from_scan

        n_points = int(msg.width) * int(msg.height)
        max_points = self.param("max_points")
        if n_points > max_points:
            raise ScanError(f"cloud has {n_points:,} points; this node accepts at most {max_points:,} "
                            "(parameter max_points)")
        scanner_pose, markers_nominal = messages.calibration_from_params(self.param("scanner_pose"),
                                                                         self.param("marker_positions"))
        points_mm, markers_mm, markers_nominal_mm = messages.scan_to_mm(msg, self.param("marker_field"),
                                                                        markers_nominal)
        pose = self.poses.resolve(self.param("part_frame"), msg.header.frame_id, msg.header.stamp,
                                  None if np.array_equal(scanner_pose, np.eye(4)) else scanner_pose)
        if self.inspection.active:
            view = ScanView(points_mm, pose.pose_mm, markers_mm, markers_nominal_mm, pose_source=pose.source)
            return {**self.inspection.add_view(msg.header, view, pose), "points": points_mm.shape[0]}
        bases, estimator = self.bases_and_estimator("")  # a lone cloud is of the default variant
        marker_std_mm, pooled = self.marker_statement(markers_mm, markers_nominal_mm)
        field, registration = field_from_scan(bases.skin, points_mm, scanner_pose=pose.pose_mm,
                                              markers_mm=markers_mm, markers_nominal_mm=markers_nominal_mm,
                                              min_coverage=self.param("min_coverage"), estimator=estimator,
                                              marker_std_mm=marker_std_mm)
        part_id = messages.part_id_of(msg)  # a cloud names no part: one id per stamp (an inspection names its own)
        self.publish_field(field, msg.header, part_id)
        return {"part_id": part_id, "points": points_mm.shape[0],
                "markers": 0 if markers_mm is None else len(markers_mm), "coverage": f"{field.coverage:.3f}",
                "noise_rms_mm": f"{field.noise_rms:.4f}", "registration": registration.method,
                "overlap": f"{registration.overlap:.3f}", "pose_source": pose.report,
                **messages.marker_check_values(pooled, registration.marker_noise)}

    def publish_field(self, field: CoreField, header: Header, part_id: str) -> None:
        header.frame_id = self.param("part_frame")
        self.field_pub.publish(messages.field_to_msg(field, header, part_id))
        self.cloud_pub.publish(self.prepared[field.model_id][1].displacement(field, header))


def main(args: list[str] | None = None) -> int:
    return spin(ScanNode, args)
