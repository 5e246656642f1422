"""The InspectPart action of the scan node: several views of one part fused into one field, answered with the
estimator's boundary state and correction for that part (docs/cell.md, DESIGN.md "Robotic cell").

- A goal (part id, variant, expected views, timeout) opens the part: from then on every cloud on ``scan/points`` is a
  view of it. Each view needs a pose from TF, ``scan/pose`` or the ``scanner_pose`` parameter (a view without one is
  refused by name, as is a view the scan step refuses); it is registered with its own pose (markers refine it) and
  turned into its field (:func:`hood_decomp.core.scan.fusion.view_field`). Feedback after every view: views received
  and refused, the coverage fused so far, the view's report (pose source or why it was refused).
- The part closes when ``expected_views`` views are fused, when its timeout passes (the result says so: "timeout: 2
  of 3 views fused", ``timed_out``), or when ``hood_decomp/close_part`` (ClosePart) is called. A cancel closes it
  without a result field.
- On closing, the views are fused (:func:`hood_decomp.core.scan.fusion.fuse_fields`), the variant's tolerance zones
  are judged on the fused field (:func:`hood_decomp.core.method.tolerance.zone_verdicts`: ``zones``, ``zones_ok``)
  and the field is published on ``hood_decomp/displacement`` with the goal's part id. The estimator node (another
  process) answers every field with a BoundaryState and a BoundaryCorrection carrying that part id and the field's
  stamp (and first a MoveVerification when it sent a correction for that part before), then reports the field on
  /diagnostics with the same stamp (``move_verified`` among its values when it verified a move). The action waits
  for the state, the correction, that report and the verification it announces (``result_timeout_s``) and returns
  them in its result. A field the estimator refuses (too little coverage, another model) is answered only on
  /diagnostics (an ERROR with the field's stamp): the action takes that as the answer and its result names the
  reason. The scan node never estimates itself: one estimator, one set of bases, one answer for the robot whether
  the field came from an inspection or a lone cloud.

Without an open goal, the node keeps one cloud, one field. One part is inspected at a time; a second goal while one
is open is rejected.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.task import Future

from hood_decomp.core.method.tolerance import zone_verdicts
from hood_decomp.core.scan.fusion import ScanView, ViewResult, fuse_fields, view_field
from hood_decomp.core.types import DisplacementField
from hood_decomp.errors import HoodDecompError, ScanError
from hood_decomp.ros.messages import M_PER_MM, marker_check_values, zone_verdicts_to_msg
from hood_decomp.ros.poses import ResolvedPose

ACTION = "hood_decomp/inspect_part"
CLOSE_SERVICE = "hood_decomp/close_part"


@dataclass
class _Part:
    """One open inspection."""

    goal_handle: Any
    part_id: str
    variant: str
    expected: int
    closed: Future
    views: list[ViewResult] = field(default_factory=list)
    reports: list[str] = field(default_factory=list)
    refused: int = 0
    header: Any = None
    timer: Any = None

    def close(self, reason: str) -> None:
        """Close the part (the first reason wins); hold the server's lock."""
        if not self.closed.done():
            self.closed.set_result(reason)


class InspectionServer:
    """The action server, the ClosePart service and the estimator's answers, attached to the scan node.

    node: the scan node; bases_and_estimator: variant -> (Bases, fitted ScanFieldEstimator of its skin) of that
    variant ("" the default; raises HoodDecompError naming the served ones for another); publish_field:
    (DisplacementField, header, part_id) -> None publishes the fused field the way the node publishes every field;
    parameter: name -> the node's current value of ``inspection_timeout_s`` (a goal's timeout when it states none)
    and ``result_timeout_s`` (module docstring), read when used; serving: () -> whether the node takes clouds (a goal
    is rejected otherwise); marker_statement: (markers (K, 3) mm or None, their nominal centres) -> (the marker
    noise to register the view with, None: estimated; the check of the scanner's stated noise over its recent
    clouds or None): the node's (:class:`~hood_decomp.core.scan.registration.MarkerNoiseHistory`); a rejected
    statement makes the view's diagnostic warn; min_view_coverage: smallest skin fraction one view must show.
    """

    def __init__(self, node: Any, *, bases_and_estimator: Callable[[str], tuple[Any, Any]],
                 publish_field: Callable[[DisplacementField, Any, str], None], parameter: Callable[[str], Any],
                 serving: Callable[[], bool],
                 marker_statement: Callable[[Any, Any], tuple[float | None, Any]] = lambda markers, nominal: (None,
                                                                                                            None),
                 min_view_coverage: float = 0.02) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from hood_decomp_msgs.action import InspectPart
        from hood_decomp_msgs.msg import BoundaryCorrection, BoundaryState, MoveVerification
        from hood_decomp_msgs.srv import ClosePart

        from hood_decomp.ros.node_common import topic_qos

        self.node = node
        self.bases_and_estimator = bases_and_estimator
        self.publish_field = publish_field
        self.parameter = parameter
        self.serving = serving
        self.marker_statement = marker_statement
        self.min_view_coverage = min_view_coverage
        self._lock = threading.Lock()  # the node's executor has two threads: a cloud and the goal may meet
        self.part: _Part | None = None
        self._reserved = False
        self._numbers = itertools.count(1)
        # stamp of a published field -> the estimator's answers so far / the future of the whole answer, while awaited
        self._answers: dict[str, dict[str, Any]] = {}
        self._waiting: dict[str, Future] = {}
        self._Action = InspectPart
        group = ReentrantCallbackGroup()  # the goal waits while the node's clouds keep coming in
        self.server = ActionServer(node, InspectPart, ACTION, execute_callback=self._execute,
                                   goal_callback=self._goal, cancel_callback=self._cancel, callback_group=group)
        self.service = node.create_service(ClosePart, CLOSE_SERVICE, self._close_part, callback_group=group)
        qos = topic_qos(10)
        self._subscriptions = [
            node.create_subscription(BoundaryState, "hood_decomp/boundary_state",
                                     lambda m: self._answer(m, "state"), qos, callback_group=group),
            node.create_subscription(BoundaryCorrection, "hood_decomp/boundary_correction",
                                     lambda m: self._answer(m, "correction"), qos, callback_group=group),
            node.create_subscription(MoveVerification, "hood_decomp/move_verification",
                                     lambda m: self._answer(m, "verification"), qos, callback_group=group),
            node.create_subscription(DiagnosticArray, "/diagnostics", self._report, 50, callback_group=group)]

    @property
    def active(self) -> bool:
        """An inspection is open: clouds are its views."""
        return self.part is not None

    # ------------------------------------------------------------------------------------------------- goals
    def _goal(self, request: Any) -> GoalResponse:
        if not self.serving():
            self.node.get_logger().warning("InspectPart rejected: the node is not active")
            return GoalResponse.REJECT
        if self.part is not None or self._reserved:
            open_id = self.part.part_id if self.part is not None else "(starting)"
            self.node.get_logger().warning(f"InspectPart rejected: part {open_id} is being inspected")
            return GoalResponse.REJECT
        if request.expected_views < 1:
            self.node.get_logger().warning("InspectPart rejected: expected_views must be >= 1")
            return GoalResponse.REJECT
        try:
            self.bases_and_estimator(request.variant)
        except HoodDecompError as error:
            self.node.get_logger().warning(f"InspectPart rejected: {error}")
            return GoalResponse.REJECT
        self._reserved = True
        return GoalResponse.ACCEPT

    def _cancel(self, goal_handle: Any) -> CancelResponse:
        with self._lock:
            if self.part is not None and self.part.goal_handle is goal_handle:
                self.part.close("canceled")
        return CancelResponse.ACCEPT

    def _close_part(self, request: Any, response: Any) -> Any:
        part = self.part
        if part is None or (request.part_id and request.part_id != part.part_id):
            response.success = False
            response.message = (f"no open inspection of part {request.part_id!r}" if request.part_id
                                else "no open inspection")
            return response
        with self._lock:
            part.close("closed by ClosePart")
        response.success = True
        response.message = f"part {part.part_id} closed with {len(part.views)} of {part.expected} view(s)"
        return response

    # ------------------------------------------------------------------------------------------------- views
    def add_view(self, header: Any, view: ScanView, pose: ResolvedPose) -> dict[str, object]:
        """One cloud of the open part: its field, or ScanError naming why it was refused (after counting it and
        sending feedback). Returns the key-values of the view's diagnostic."""
        with self._lock:
            part = self.part
        if part is None:  # closed since the node asked
            raise ScanError("the inspection closed before this cloud was taken; it was not used")
        number = len(part.views) + part.refused + 1
        name = f"view {number} of part {part.part_id} ({header.frame_id or 'no frame'}, " \
               f"{_stamp(header.stamp)})"
        try:
            if view.scanner_pose is None:
                raise ScanError(f"{name}: no pose from TF, scan/pose or the scanner_pose parameter "
                                f"({'; '.join(pose.skipped) or 'no source'})")
            bases, estimator = self.bases_and_estimator(part.variant)
            marker_std_mm, pooled = self.marker_statement(view.markers_mm, view.markers_nominal_mm)
            result = view_field(bases.skin, ScanView(view.points_mm, view.scanner_pose, view.markers_mm,
                                               view.markers_nominal_mm, name=name, pose_source=pose.source),
                                estimator=estimator, min_coverage=self.min_view_coverage,
                                marker_std_mm=marker_std_mm)
        except ScanError as error:
            part.refused += 1
            part.reports.append(f"refused: {error}")
            self._feedback(part, f"refused: {error}")
            raise
        with self._lock:
            if part.closed.done():  # closed (timeout, ClosePart, cancel) while this view was processed
                raise ScanError(f"{name}: the inspection closed while this view was processed; it was not used")
            part.views.append(result)
            part.header = header
        registration = result.registration.method
        report = f"{name}: {pose.report}, registered by {registration}, coverage {result.field.coverage:.3f}"
        if result.pose_correction_mm == result.pose_correction_mm:  # not NaN: markers refined the pose
            report += (f", markers moved it {result.pose_correction_mm:.3f} mm / {result.pose_correction_deg:.4f} deg "
                       "from its pose")
        marker_check = marker_check_values(pooled, result.registration.marker_noise)
        if "warning" in marker_check:
            report += f", {marker_check['warning']}"
        part.reports.append(report)
        coverage = self._feedback(part, report)
        if len(part.views) >= part.expected:
            with self._lock:
                part.close("complete")
        return {"part_id": part.part_id, "view": number, "pose_source": pose.source, "registration": registration,
                "view_coverage": f"{result.field.coverage:.3f}", "fused_coverage": f"{coverage:.3f}",
                **marker_check}

    def _feedback(self, part: _Part, last: str) -> float:
        bases, _ = self.bases_and_estimator(part.variant)
        coverage = fuse_fields([v.field for v in part.views], bases.skin).coverage if part.views else 0.0
        part.goal_handle.publish_feedback(self._Action.Feedback(
            views_received=len(part.views) + part.refused, views_refused=part.refused, coverage=float(coverage),
            last_view=last[:1000]))
        return coverage

    # ------------------------------------------------------------------------------------------------- answers
    def _answer(self, message: Any, kind: str) -> None:
        """A state, correction or verification: kept when it answers a field this server awaits (by its stamp)."""
        stamp = _stamp(message.header.stamp)
        with self._lock:
            if stamp in self._waiting:
                self._answers[stamp][kind] = message
                self._complete(stamp)

    def _report(self, message: Any) -> None:
        """The estimator's report of a field this server awaits: an ERROR is its refusal (the answer); an OK says it
        is done with the field, and whether a verification belongs to the answer (``move_verified``)."""
        for status in message.status:
            if not status.name.endswith("_estimator"):
                continue
            values = {kv.key: kv.value for kv in status.values}
            stamp = values.get("stamp", "")
            with self._lock:
                future = self._waiting.get(stamp)
                if future is None or future.done():
                    continue
                if status.level == status.ERROR:
                    future.set_result({"refused": status.message})
                else:
                    self._answers[stamp]["report"] = values
                    self._complete(stamp)

    def _complete(self, stamp: str) -> None:
        """Resolve the awaited answer of ``stamp`` once it is whole; hold the lock."""
        answers, future = self._answers[stamp], self._waiting[stamp]
        whole = {"state", "correction", "report"} <= set(answers) and (
            "move_verified" not in answers["report"] or "verification" in answers)
        if whole and not future.done():
            future.set_result(answers)

    def _timer(self, seconds: float, future: Future, value: object) -> Any:
        def fire() -> None:
            timer.cancel()
            with self._lock:
                if not future.done():
                    future.set_result(value)

        timer = self.node.create_timer(seconds, fire)
        return timer

    # ------------------------------------------------------------------------------------------------- execution
    async def _execute(self, goal_handle: Any) -> Any:
        request = goal_handle.request
        part_id = request.part_id or f"part-{self.node.get_clock().now().nanoseconds}-{next(self._numbers)}"
        timeout = request.timeout.sec + request.timeout.nanosec * 1e-9 or self.parameter("inspection_timeout_s")
        part = _Part(goal_handle, part_id, request.variant, int(request.expected_views), Future())
        part.timer = self._timer(timeout, part.closed, "timeout")
        with self._lock:
            self.part, self._reserved = part, False
        self.node.get_logger().info(f"inspection of part {part_id}: {part.expected} view(s) within {timeout:g} s")
        try:
            reason = await part.closed
        finally:
            part.timer.cancel()
            self.node.destroy_timer(part.timer)
            with self._lock:
                self.part = None
        result = self._Action.Result(part_id=part_id, variant=request.variant, views_expected=part.expected,
                                     views_used=len(part.views), views_refused=part.refused,
                                     view_reports=list(part.reports), timed_out=reason == "timeout")
        counted = f"{len(part.views)} of {part.expected} view(s) fused"
        if reason == "canceled":
            result.message = f"canceled: {counted}"
            goal_handle.canceled()
            return result
        if not part.views:
            result.message = f"{reason}: no view fused ({part.refused} refused)"
            goal_handle.abort()
            return result
        bases, _ = self.bases_and_estimator(part.variant)
        fused = fuse_fields([v.field for v in part.views], bases.skin)
        result.model_id, result.coverage = fused.model_id, float(fused.coverage)
        result.noise_rms = float(fused.noise_rms) * M_PER_MM
        verdicts = zone_verdicts(fused, bases.tolerance_zones)
        result.zones, result.zones_ok = zone_verdicts_to_msg(verdicts), all(v.ok for v in verdicts)
        zones = "; ".join(f"zone {v.name} NOK: {v.reason}" for v in verdicts if not v.ok)
        header = part.header
        stamp = _stamp(header.stamp)
        with self._lock:
            answer = self._waiting[stamp] = Future()
            self._answers[stamp] = {}
        self.publish_field(fused, header, part_id)
        result_timeout = self.parameter("result_timeout_s")
        timer = self._timer(result_timeout, answer, None)
        try:
            answers = await answer
        finally:
            timer.cancel()
            self.node.destroy_timer(timer)
            with self._lock:
                self._waiting.pop(stamp, None)
                partial = self._answers.pop(stamp, {})
        if answers is not None and "refused" in answers:
            result.message = _join(f"{reason}: {counted}, field published, the estimator refused it: "
                                   f"{answers['refused']}", zones)
            goal_handle.abort()
            return result
        if answers is None and not {"state", "correction"} <= set(partial):
            result.message = _join(f"{reason}: {counted}, field published, but no boundary state and correction for "
                                   f"part {part_id} within {result_timeout:g} s (is the estimator node running?)",
                                   zones)
            goal_handle.abort()
            return result
        late = "" if answers is not None else (f"the estimator's report (and a verification it may announce) did not "
                                               f"come within {result_timeout:g} s")
        answers = answers or partial
        result.boundary_state, result.boundary_correction = answers["state"], answers["correction"]
        if "verification" in answers:
            result.verification = answers["verification"]
        result.success = True
        result.message = _join(f"{reason}: {counted}", result.verification.summary, zones, late)
        goal_handle.succeed()
        return result


def _stamp(stamp: Any) -> str:
    """A header stamp as the estimator's diagnostics write it (``<sec>.<nanosec>``)."""
    return f"{stamp.sec}.{stamp.nanosec:09d}"


def _join(*parts: str) -> str:
    return "; ".join(part for part in parts if part)
