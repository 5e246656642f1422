"""Estimator node: hood_decomp/displacement -> hood_decomp/boundary_state + hood_decomp/boundary_correction.

Least squares on the bases (the contact-aware estimator by default, the paper's PCA estimator on request), then the
correction for the fixture adjustment robot with ``safe_to_apply`` and its reasons (hood_decomp.core.method.correction).
Both results are published transient-local (the latest results).
"""

from __future__ import annotations

from hood_decomp_msgs.msg import BoundaryCorrection, BoundaryState, DisplacementField
from rclpy.parameter import Parameter

from hood_decomp.core.method.correction import CorrectionPolicy, plan_correction
from hood_decomp.ros import messages
from hood_decomp.ros.node_common import HoodNode, declare, spin

METHODS = ("contact", "pca")


class EstimatorNode(HoodNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_estimator")
        declare(self, "method", "contact", "estimator: 'contact' (contact-aware, default) or 'pca' (the paper's "
                "eqs. 4-5)")
        declare(self, "min_coverage", 0.6, "smallest seen fraction of the skin to act on", 0.0, 1.0)
        declare(self, "max_std_mm", CorrectionPolicy.max_std_mm, "largest uncertainty (mm, 1 sigma) to act on",
                0.0, 100.0)
        declare(self, "range_tolerance_mm", 0.02, "tolerance (mm) on the declared parameter ranges", 0.0, 10.0)
        self.state_pub = self.correction_pub = None

    def check_parameter(self, parameter: Parameter) -> str:
        if parameter.name == "method" and parameter.value not in METHODS:
            return f"one of {', '.join(METHODS)}, got {parameter.value!r}"
        return ""

    def policy(self) -> CorrectionPolicy:
        return CorrectionPolicy(min_coverage=self.param("min_coverage"), max_std_mm=self.param("max_std_mm"),
                                range_tolerance_mm=self.param("range_tolerance_mm"))

    def configure_node(self) -> None:
        self.state_pub = self.publisher(BoundaryState, "hood_decomp/boundary_state", latest=True)
        self.correction_pub = self.publisher(BoundaryCorrection, "hood_decomp/boundary_correction", latest=True)

    def activate_node(self) -> None:
        self.subscription(DisplacementField, "hood_decomp/displacement", self.guarded("estimation", self.on_field))

    def on_field(self, msg: DisplacementField) -> dict[str, object]:
        from hood_decomp.core.method.bases import estimate_field

        policy = self.policy()
        estimate = estimate_field(self.require_bases(), messages.msg_to_field(msg), method=self.param("method"),
                                  min_coverage=policy.min_coverage)
        correction = plan_correction(estimate, policy)
        part_id = messages.part_id_of(msg)
        self.state_pub.publish(messages.estimate_to_msg(estimate, msg.header, part_id))
        self.correction_pub.publish(messages.correction_to_msg(correction, msg.header, part_id))
        return {"part_id": part_id, "residual_rms_mm": f"{estimate.residual_rms:.4f}",
                "within_model": estimate.within_model, "safe_to_apply": correction.safe_to_apply,
                "reason": correction.reason}


def main(args: list[str] | None = None) -> int:
    return spin(EstimatorNode, args)
