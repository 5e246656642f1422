"""Estimator node: hood_decomp/displacement -> hood_decomp/boundary_state + hood_decomp/boundary_correction.

Least squares on the bases (the contact-aware estimator by default, the paper's PCA estimator on request), then the
correction for the fixture adjustment robot with ``safe_to_apply`` and its reasons (hood_decomp.core.correction).
"""

from __future__ import annotations

from hood_decomp_msgs.msg import BoundaryCorrection, BoundaryState, DisplacementField
from rclpy.node import Node

from hood_decomp.core.correction import CorrectionPolicy, plan_correction
from hood_decomp.errors import HoodDecompError
from hood_decomp.ros import messages
from hood_decomp.ros.node_common import (
    ERROR,
    OVERRIDABLE,
    Diagnostics,
    declare,
    guarded,
    load_bases_or_reason,
    spin,
    topic_qos,
)


class EstimatorNode(Node):
    def __init__(self) -> None:
        super().__init__("hood_decomp_estimator")
        self.bases_path = declare(self, "bases", "", "path of the bases file (hood-decomp bases --out)")
        self.method = declare(self, "method", "contact", "estimator: 'contact' (contact-aware, default) or 'pca' "
                              "(the paper's eqs. 4-5)")
        self.policy = CorrectionPolicy(
            min_coverage=declare(self, "min_coverage", 0.6, "smallest seen fraction of the skin to act on", 0.0, 1.0),
            max_std_mm=declare(self, "max_std_mm", 0.05, "largest uncertainty (mm, 1 sigma) to act on", 0.0, 100.0),
            range_tolerance_mm=declare(self, "range_tolerance_mm", 0.02,
                                       "tolerance (mm) on the declared parameter ranges", 0.0, 10.0),
        )
        depth = declare(self, "queue_depth", 10, "messages held per topic while the node is busy", 1, 1000)
        self.diagnostics = Diagnostics(self)
        self.bases, self.bases_error = load_bases_or_reason(self.bases_path)
        if self.bases_error:
            self.diagnostics.report(ERROR, self.bases_error)
        self.state_pub = self.create_publisher(BoundaryState, "hood_decomp/boundary_state", topic_qos(depth),
                                               qos_overriding_options=OVERRIDABLE)
        self.correction_pub = self.create_publisher(BoundaryCorrection, "hood_decomp/boundary_correction",
                                                    topic_qos(depth), qos_overriding_options=OVERRIDABLE)
        self.create_subscription(DisplacementField, "hood_decomp/displacement",
                                 guarded(self, self.diagnostics, "estimation", self.on_field), topic_qos(depth),
                                 qos_overriding_options=OVERRIDABLE)

    def on_field(self, msg: DisplacementField) -> dict[str, object]:
        from hood_decomp.core.bases import estimate_field

        if self.bases is None:
            raise HoodDecompError(self.bases_error)
        estimate = estimate_field(self.bases, messages.msg_to_field(msg), method=self.method,
                                  min_coverage=self.policy.min_coverage)
        correction = plan_correction(estimate, self.policy)
        self.state_pub.publish(messages.estimate_to_msg(estimate, msg.header))
        self.correction_pub.publish(messages.correction_to_msg(correction, msg.header))
        return {"residual_rms_mm": f"{estimate.residual_rms:.4f}", "within_model": estimate.within_model,
                "safe_to_apply": correction.safe_to_apply, "reason": correction.reason}


def main(args: list[str] | None = None) -> int:
    return spin(EstimatorNode, args)
