"""Estimator node: hood_decomp/displacement -> hood_decomp/boundary_state + hood_decomp/boundary_correction
(+ hood_decomp/move_verification for a part that received a correction before).

Least squares on the bases (the contact-aware estimator by default, the paper's PCA estimator on request), then the
correction for the fixture adjustment robot with ``safe_to_apply`` and its reasons (hood_decomp.core.method.correction),
each move capped to the boundary's maximum step per cycle (the rest left for the next cycle, and said so). The node
remembers the last estimate and correction per part id; the next inspection of that part compares the measured change
with the predicted one and names a failed or slipped move. All results are published transient-local.

With the parameter ``history`` (a path), every estimate is also appended to that results history (SQLite,
docs/history_schema.md) through the writer the shift uses (hood_decomp.io.history), naming the reference the field was
made relative to and the bases' calibration: a database that cannot be written
(a bad path, a lock held too long by a reader) is an ERROR on /diagnostics, the node keeps serving, and the parts
wait in memory until the database can be written again (retried with the next part and every few seconds).
A measured effect (a parameter without a boundary, of bases rebuilt by the shift) is flagged in the boundary state
and the correction (``measured_effect``) and never corrected.

The parameter ``components`` "xyz" fits all three displacement components of fields that carry them
(``displacement_3d``: simulated or FE fields without an error model, core.method.bases.estimate_field); a scan's
field is then refused by name, as ``hood-decomp estimate --components xyz`` refuses it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, NamedTuple

import numpy as np
from hood_decomp_msgs.msg import BoundaryCorrection, BoundaryState, DisplacementField, MoveVerification
from rclpy.parameter import Parameter
from std_msgs.msg import Header

from hood_decomp.core.method.coarsening import coarsening_stride, parse_coarsening
from hood_decomp.core.method.correction import CorrectionPolicy, limit_steps, plan_correction, verify_move
from hood_decomp.core.method.estimation import COMPONENTS
from hood_decomp.core.types import BoundaryCorrection as CoreCorrection
from hood_decomp.core.types import DisplacementField as CoreField
from hood_decomp.core.types import FieldErrorModel, ParameterEstimate
from hood_decomp.errors import BasisError, HoodDecompError
from hood_decomp.io.history import HistoryWriter, PartRecord, bases_file_id, inspection_record
from hood_decomp.ros import messages
from hood_decomp.ros.node_common import (
    ERROR,
    ReferencedNode,
    declare,
    declare_list,
    parse_entries,
    spin,
    through_middleware,
)

METHODS = ("contact", "pca")
#: seconds between two retries of a history that could not be written
HISTORY_RETRY_S = 5.0


class _Sent(NamedTuple):
    """What the node told the robot for a part: the estimate it came from, the correction, the field's stamp, the
    label of the reference the field was made relative to ("" none)."""

    estimate: ParameterEstimate
    correction: CoreCorrection
    stamp: Any
    reference: str


def parse_step_limits(entries: list[str]) -> dict[str, float]:
    """``["LABEL=MM", ...]`` -> {label: mm}; a malformed entry is a ValueError naming it."""
    limits = {}
    for label, value in parse_entries(entries, "MM").items():
        try:
            limits[label] = float(value)
        except ValueError:
            limits[label] = float("nan")
        if not np.isfinite(limits[label]) or limits[label] < 0:
            raise ValueError(f"{label}={value}: expected MM a finite number >= 0")
    return limits


class EstimatorNode(ReferencedNode):
    def __init__(self) -> None:
        super().__init__("hood_decomp_estimator")
        declare(self, "method", "contact", "estimator: 'contact' (contact-aware, default) or 'pca' (the paper's "
                "eqs. 4-5)")
        declare(self, "components", "normal", "displacement components fitted: 'normal' (default; a scan measures "
                "normal distances) or 'xyz', all three of a field that carries them (a simulated or FE field "
                "without an error model; other fields are refused)")
        declare(self, "min_coverage", 0.6, "smallest seen fraction of the skin to act on", 0.0, 1.0)
        declare(self, "coarsen", "auto", "the paper's coarsening of the input field: 'auto' (a quarter of the nodes "
                "of a scan's field on a skin above 100,000 nodes, every node otherwise) or an integer stride >= 1 "
                "(1: every node)")
        declare(self, "max_std_mm", CorrectionPolicy.max_std_mm, "largest uncertainty (mm, 1 sigma) to act on",
                0.0, 100.0)
        declare(self, "range_tolerance_mm", 0.02, "tolerance (mm) on the declared parameter ranges", 0.0, 10.0)
        declare(self, "max_step_mm", 0.0, "largest move (mm) of any boundary per correction cycle; the rest is left "
                "for the next cycle (0: no limit)", 0.0, 100.0)
        declare_list(self, "max_step_by_boundary", Parameter.Type.STRING_ARRAY, "per-boundary maximum step per "
                     "cycle, LABEL=MM entries (override max_step_mm for that boundary)")
        declare(self, "verify_sigmas", 3.0, "a move counts as achieved within this many stds of the measured change "
                "minus the predicted one", 0.5, 10.0)
        declare(self, "verify_min_tolerance_mm", 0.005, "smallest tolerance (mm) of the move verification (the "
                "robot's repeatability; the std of a noise-free field is 0)", 0.0, 10.0)
        declare(self, "remembered_parts", 1000, "parts whose last correction is kept for the verification of the "
                "next inspection (oldest forgotten first)", 1, 1_000_000)
        declare(self, "history", "", "results history (SQLite file, created when missing) every estimate is "
                "appended to, as hood-decomp shift writes it (docs/history_schema.md); empty: none")
        declare(self, "history_max_pending", 1000, "parts kept in memory while the history cannot be written (the "
                "oldest beyond are dropped and counted)", 1, 1_000_000)
        self.sent: OrderedDict[str, _Sent] = OrderedDict()
        self.state_pub = self.correction_pub = self.verification_pub = None
        self.writer: HistoryWriter | None = None
        self.history_lock = threading.RLock()  # the retry timer and the subscription run in different threads
        self.bases_paths: dict[str, str] = {}  # model_id -> its bases file
        self.bases_ids: dict[str, str] = {}  # model_id -> fingerprint of its bases file (the history's bases_id)
        self.received = 0

    def check_parameter(self, parameter: Parameter) -> str:
        if parameter.name == "method" and parameter.value not in METHODS:
            return f"one of {', '.join(METHODS)}, got {parameter.value!r}"
        if parameter.name == "components" and parameter.value not in COMPONENTS:
            return f"one of {', '.join(COMPONENTS)}, got {parameter.value!r}"
        if parameter.name in ("coarsen", "components"):  # a stride > 1 with xyz would refuse every field
            values = {name: self.param(name) if self.has_parameter(name) else default  # while declaring
                      for name, default in (("coarsen", "auto"), ("components", "normal"))}
            values[parameter.name] = parameter.value
            try:
                coarsening_stride(parse_coarsening(values["coarsen"]), 0, values["components"])
            except BasisError as error:
                return str(error)
        if parameter.name == "max_step_by_boundary":
            try:
                parse_step_limits(list(parameter.value or []))
            except ValueError as error:
                return str(error)
        return super().check_parameter(parameter)

    def policy(self) -> CorrectionPolicy:
        return CorrectionPolicy(min_coverage=self.param("min_coverage"), max_std_mm=self.param("max_std_mm"),
                                range_tolerance_mm=self.param("range_tolerance_mm"))

    def step_limits(self, names: tuple[str, ...]) -> np.ndarray:
        """(P,) mm per boundary of ``names``: its LABEL=MM entry, else max_step_mm (0: no limit)."""
        by_name = parse_step_limits(list(self.param("max_step_by_boundary")))
        return np.array([by_name.get(name, self.param("max_step_mm")) for name in names])

    def configure_node(self) -> None:
        super().configure_node()  # the references, read with the new bases
        self.sent.clear()
        for bases in self.variant_bases.values():  # fitted now, so the first field is answered at steady speed
            bases.prepare_estimation(self.param("method"), self.param("min_coverage"),
                                     components=self.param("components"),
                                     coarsen=parse_coarsening(self.param("coarsen")))
            try:
                self.warm_up(bases)
            except HoodDecompError as error:  # the bases serve real fields all the same: said, not fatal
                self.get_logger().warning(f"warm-up of {bases.model_id} failed: {error}")
        self.state_pub = self.publisher(BoundaryState, "hood_decomp/boundary_state", latest=True)
        self.correction_pub = self.publisher(BoundaryCorrection, "hood_decomp/boundary_correction", latest=True)
        self.verification_pub = self.publisher(MoveVerification, "hood_decomp/move_verification", latest=True)
        paths = {"": self.param("bases"), **parse_entries(list(self.param("variants")), "PATH")}
        self.bases_paths = {self.variant_bases[variant].model_id: path for variant, path in paths.items()}
        self.bases_ids.clear()

    def activate_node(self) -> None:
        self.subscription(DisplacementField, "hood_decomp/displacement", self.guarded("estimation", self.on_field))
        self.timer(HISTORY_RETRY_S, self.retry_history)

    def history_writer(self) -> HistoryWriter | None:
        """The writer of the ``history`` parameter's database (None when empty); a new path takes the pending parts."""
        with self.history_lock:
            return self._history_writer()

    def _history_writer(self) -> HistoryWriter | None:
        path = self.param("history")
        if self.writer is not None and str(self.writer.path) != path:
            self.writer.close()
            pending, self.writer = self.writer.pending, None
            if path:
                self.writer = HistoryWriter(path)
                self.writer.pending.extend(pending)
        elif self.writer is None and path:
            self.writer = HistoryWriter(path)
        if self.writer is not None:
            self.writer.max_pending = self.param("history_max_pending")
        return self.writer

    def report_history(self, problem: str, stamp: Any = None) -> None:
        writer = self.writer
        self.get_logger().error(problem)
        self.diagnostics.report(ERROR, problem, stamp, history=str(writer.path), history_pending=len(writer.pending),
                                history_dropped=writer.dropped)

    def retry_history(self) -> None:
        with self.history_lock:
            writer = self.history_writer()
            problem = writer.flush() if writer is not None and writer.pending else ""
        if problem:
            self.report_history(problem)

    def record(self, msg: DisplacementField, field: CoreField, estimate: ParameterEstimate,
               correction: CoreCorrection, part_id: str, reference: str) -> dict[str, object]:
        """Append the part to the live history (when one is named), with the ``reference`` label its field was made
        relative to and its bases' calibration; its key-values for the OK diagnostic."""
        writer = self.history_writer()
        if writer is None:
            return {}
        from hood_decomp.core.method.bases import analyse_estimate
        from hood_decomp.core.method.residual import noise_level
        from hood_decomp.io.bases import calibration_id

        bases = self.bases_for_model(msg.model_id)
        stamp = msg.header.stamp
        stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
        # each inspection is its own source (node and field stamp): a part inspected again after a correction gets a
        # row per inspection, the same field received twice (republished) one row
        base = PartRecord(source=f"live:{self.get_fully_qualified_name()}@{stamp_ns}", part_id=part_id,
                          message=self.received, stamp_ns=stamp_ns,
                          shift=f"live {self.get_name()}", model_id=estimate.model_id,
                          bases_id=self.bases_id(estimate.model_id), calibration=calibration_id(bases),
                          reference=reference, method=estimate.method)
        analysis = analyse_estimate(bases, estimate, noise_level(field.noise_rms)[0])
        with self.history_lock:
            problem = writer.append(inspection_record(base, estimate, analysis, correction))
        if problem:
            self.report_history(problem, stamp)
        return {"history_written": not problem, "history_pending": len(writer.pending)}

    def bases_id(self, model_id: str) -> str:
        """The fingerprint of the bases file serving ``model_id``, read once (only when a history is written)."""
        if model_id not in self.bases_ids:
            self.bases_ids[model_id] = bases_file_id(self.bases_paths[model_id])
        return self.bases_ids[model_id]

    def on_deactivate(self, state: Any) -> Any:
        self.retry_history()  # what is still pending stays in memory for the next activation
        if self.writer is not None:
            self.writer.close()
        return super().on_deactivate(state)

    def answer(self, msg: DisplacementField) -> tuple[CoreField, ParameterEstimate, CoreCorrection, str]:
        """A field message -> the field (reference-relative when the part or the cell has a reference), its
        estimate, the step-limited correction and the reference used (nothing published or kept)."""
        from hood_decomp.core.method.bases import estimate_field

        policy = self.policy()
        bases, field, reference = self.field_of(msg)
        estimate = estimate_field(bases, field, method=self.param("method"), min_coverage=policy.min_coverage,
                                  components=self.param("components"),
                                  coarsen=parse_coarsening(self.param("coarsen")))
        correction = limit_steps(plan_correction(estimate, policy), self.step_limits(estimate.names))
        return field, estimate, correction, reference

    def warm_up(self, bases: Any) -> None:
        """One synthetic field of ``bases`` (the PCA mean field, scan-like node errors; with ``components`` "xyz" its
        3D mean field, no error model, as a simulated field) through :meth:`answer` and the outgoing messages, nothing
        published, so that the first real field pays no first use (issue 19)."""
        from hood_decomp.core.scan import smoothing_bias_correlation

        n = bases.skin.n_nodes
        if self.param("components") == "xyz":
            vectors = np.array(bases.pca.mean_field_3d_, dtype=float)
            field = CoreField(bases.model_id, np.einsum("na,na->n", vectors, bases.skin.normals), 1.0, float("nan"),
                              displacement=vectors)
        else:
            errors = FieldErrorModel("scan", np.full(n, 0.005), np.full(n, 20.0), 5.0,
                                     bias_correlation=smoothing_bias_correlation(bases.skin))
            field = CoreField(bases.model_id, np.array(bases.pca.mean_field_, dtype=float), 1.0, 0.05, errors)
        header = Header()
        _, estimate, correction, _ = self.answer(through_middleware(messages.field_to_msg(field, header, "warm-up")))
        messages.estimate_to_msg(estimate, header, "warm-up")
        messages.correction_to_msg(correction, header, "warm-up")

    def on_field(self, msg: DisplacementField) -> dict[str, object]:
        self.received += 1
        field, estimate, correction, reference = self.answer(msg)
        part_id = messages.part_id_of(msg)
        values: dict[str, object] = {"part_id": part_id, "reference": reference or "none"}
        earlier = self.sent.pop(part_id, None)
        if earlier is not None and earlier.reference != reference:
            # two estimates relative to different references differ by the references' difference, not by the move
            # no move_verified: it announces a MoveVerification (the inspection action waits for one), none comes
            values["move_summary"] = "not verified: reference changed between inspections"
            values["warning"] = (f"reference changed between inspections ({earlier.reference or 'none'} -> "
                                 f"{reference or 'none'}): the correction sent for this part is not verified")
        elif earlier is not None:
            verification = verify_move(earlier.estimate, earlier.correction, estimate,
                                       self.param("verify_sigmas"), self.param("verify_min_tolerance_mm"))
            self.verification_pub.publish(messages.verification_to_msg(verification, msg.header, part_id,
                                                                       earlier.stamp))
            values["move_verified"] = verification.all_achieved
            values["move_summary"] = verification.summary or "every commanded move achieved"
        self.sent[part_id] = _Sent(estimate, correction, msg.header.stamp, reference)
        while len(self.sent) > self.param("remembered_parts"):
            self.sent.popitem(last=False)
        self.state_pub.publish(messages.estimate_to_msg(estimate, msg.header, part_id, reference))
        self.correction_pub.publish(messages.correction_to_msg(correction, msg.header, part_id))
        # after publishing: the robot first
        values.update(self.record(msg, field, estimate, correction, part_id, reference))
        return {**values, "residual_rms_mm": f"{estimate.residual_rms:.4f}", "within_model": estimate.within_model,
                "safe_to_apply": correction.safe_to_apply, "reason": correction.reason}


def main(args: list[str] | None = None) -> int:
    return spin(EstimatorNode, args)
