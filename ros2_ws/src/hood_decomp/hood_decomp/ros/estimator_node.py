"""Estimator node: hood_decomp/displacement -> hood_decomp/boundary_state + hood_decomp/boundary_correction.

Least squares on the bases (the contact-aware estimator by default, the paper's PCA estimator on request), then the
correction for the fixture adjustment robot with ``safe_to_apply`` and its reasons (hood_decomp.core.method.correction).
"""

from __future__ import annotations

from hood_decomp_msgs.msg import BoundaryCorrection, BoundaryState, DisplacementField

from hood_decomp.core.method.correction import CorrectionPolicy, plan_correction
from hood_decomp.ros import messages
from hood_decomp.ros.node_common import HoodNode, declare, spin


class EstimatorNode(HoodNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_estimator")
        self.method = declare(self, "method", "contact", "estimator: 'contact' (contact-aware, default) or 'pca' "
                              "(the paper's eqs. 4-5)")
        self.policy = CorrectionPolicy(
            min_coverage=declare(self, "min_coverage", 0.6, "smallest seen fraction of the skin to act on", 0.0, 1.0),
            max_std_mm=declare(self, "max_std_mm", CorrectionPolicy.max_std_mm,
                               "largest uncertainty (mm, 1 sigma) to act on", 0.0, 100.0),
            range_tolerance_mm=declare(self, "range_tolerance_mm", 0.02,
                                       "tolerance (mm) on the declared parameter ranges", 0.0, 10.0),
        )
        self.state_pub = self.publisher(BoundaryState, "hood_decomp/boundary_state")
        self.correction_pub = self.publisher(BoundaryCorrection, "hood_decomp/boundary_correction")
        self.subscription(DisplacementField, "hood_decomp/displacement", self.guarded("estimation", self.on_field))

    def on_field(self, msg: DisplacementField) -> dict[str, object]:
        from hood_decomp.core.method.bases import estimate_field

        estimate = estimate_field(self.require_bases(), messages.msg_to_field(msg), method=self.method,
                                  min_coverage=self.policy.min_coverage)
        correction = plan_correction(estimate, self.policy)
        part_id = messages.part_id_of(msg)
        self.state_pub.publish(messages.estimate_to_msg(estimate, msg.header, part_id))
        self.correction_pub.publish(messages.correction_to_msg(correction, msg.header, part_id))
        return {"part_id": part_id, "residual_rms_mm": f"{estimate.residual_rms:.4f}",
                "within_model": estimate.within_model, "safe_to_apply": correction.safe_to_apply,
                "reason": correction.reason}


def main(args: list[str] | None = None) -> int:
    return spin(EstimatorNode, args)
