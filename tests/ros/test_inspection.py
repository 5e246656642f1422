"""The InspectPart action against a client written here in plain rclpy, with the real scan and estimator nodes as
processes (Fast DDS, loopback): goal, feedback, result, cancel, ClosePart, timeout with fewer views than expected,
a view without a pose refused by name, tolerance zones, the verification of a half-done move, and two variants served
by one node. Truth: the FE state the synthetic scanner scanned, its FE field, and the scanner's true poses (sent on
scan/pose, and once as a static transform on /tf_static)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.action", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
from action_msgs.msg import GoalStatus
from builtin_interfaces.msg import Duration, Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import TransformStamped
from hood_decomp_msgs.action import InspectPart
from hood_decomp_msgs.msg import DisplacementField
from hood_decomp_msgs.srv import ClosePart
from rclpy.action import ActionClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from tf2_msgs.msg import TFMessage

from hood_decomp.core.types import ToleranceZone
from hood_decomp.io.bases import save_bases
from hood_decomp.ros import messages
from hood_decomp.ros.launcher import start_nodes, stop_nodes
from hood_decomp.ros.participant import Participant
from hood_decomp.ros.poses import matrix_quaternion
from hood_decomp.ros.scan_bag import scan_cloud
from tests.multiview import scanned_part

pytestmark = pytest.mark.ros

TRUTH = {"HINGE_Y": -0.3, "LOCK_L": 0.4}
ZONE_HALF_WIDTH_MM = 150.0


def _box(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Skin nodes within ZONE_HALF_WIDTH_MM of ``centre`` in x and y (the zone's region, chosen here)."""
    return np.flatnonzero(np.all(np.abs(points[:, :2] - centre[:2]) <= ZONE_HALF_WIDTH_MM, axis=1))


@dataclasses.dataclass(frozen=True)
class Zoned:
    """The bases the nodes serve: the coarse hood with two zones (default variant) and the 20 x 20 hood (the same
    surface on another mesh, another model_id) with one (variant H20); ``truth`` the scanned part's FE normal
    displacement (N,) mm."""

    default_path: object
    h20_path: object
    h20_model_id: str
    zones: tuple[ToleranceZone, ...]
    truth: np.ndarray


@pytest.fixture(scope="module")
def zoned(coarse_hood, tmp_path_factory):
    """Zone "lock_corner" around the largest deviation of the scanned part, limits half of it (out of tolerance);
    zone "centre" with +-5 mm (in tolerance); the H20 variant's one zone "whole" of +-5 mm."""
    from hood_decomp.core.fe.ensemble import solve_members
    from tests.hood20 import hood20

    state = np.array([TRUTH.get(name, 0.0) for name in coarse_hood.reduced.names])
    truth = solve_members(coarse_hood.reduced, state[None]).normal_displacement[0]  # what scanned_part scans
    points = coarse_hood.skin.points
    peak = int(np.argmax(np.abs(truth)))
    half = 0.5 * abs(truth[peak])
    zones = (ToleranceZone("lock_corner", _box(points, points[peak]), -half, half, 0.5, "{}"),
             ToleranceZone("centre", _box(points, points.mean(axis=0)), -5.0, 5.0, 0.5, "{}"))
    directory = tmp_path_factory.mktemp("zoned_bases")
    default_path, h20_path = directory / "hood.h5", directory / "hood20.h5"
    save_bases(default_path, dataclasses.replace(coarse_hood.bases, tolerance_zones=zones))
    h20 = hood20()
    whole = ToleranceZone("whole", np.arange(h20.skin.n_nodes), -5.0, 5.0, 0.5, "{}")
    save_bases(h20_path, dataclasses.replace(h20.bases, tolerance_zones=(whole,)))
    return Zoned(default_path, h20_path, h20.bases.model_id, zones, truth)


@pytest.fixture(scope="module")
def cell(coarse_hood, zoned, tmp_path_factory):
    """The scan and estimator nodes (serving the default variant and H20), a plain rclpy client, three partial
    views of one part (with markers)."""
    member, scans = scanned_part(coarse_hood, TRUTH, 30, marker_noise_mm=0.01, n_holes=0)
    directory = tmp_path_factory.mktemp("inspection")
    _, markers = messages.calibration_to_params(np.eye(4), {int(i): p for s in scans
                                                            for i, p in zip(s.marker_ids, s.markers_nominal,
                                                                            strict=True)})
    params = directory / "params.yaml"
    params.write_text(f"/**:\n  ros__parameters:\n    variants: [\"H20={zoned.h20_path}\"]\n"
                      "hood_decomp_scan:\n  ros__parameters:\n"
                      f"    marker_positions: {json.dumps(markers)}\n    marker_field: marker_id\n"
                      "    result_timeout_s: 60.0\n"
                      # three 60k-point views state 0.02 mm on LOCK_L: let the robot act on it
                      "hood_decomp_estimator:\n  ros__parameters:\n    max_std_mm: 0.05\n")
    processes = start_nodes(zoned.default_path, params_file=params, nodes=("scan_node", "estimator_node"),
                            log_dir=directory)
    peer = Participant("inspection_client")
    client = ActionClient(peer.node, InspectPart, "hood_decomp/inspect_part")
    close = peer.node.create_client(ClosePart, "hood_decomp/close_part")
    peer.publisher("scan/points", PointCloud2)
    peer.publisher("scan/pose", TransformStamped)
    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    peer.publishers["/tf_static"] = peer.node.create_publisher(TFMessage, "/tf_static", latched)
    fields = peer.collect("hood_decomp/displacement", DisplacementField)
    peer.diagnostics = peer.collect("/diagnostics", DiagnosticArray)
    ready = peer.connected(["scan/points", "scan/pose"], [], 90.0) and peer.wait(
        lambda: client.server_is_ready() and close.service_is_ready()
        and peer.node.count_subscribers("hood_decomp/displacement") >= 2, 90.0)
    yield peer, client, close, scans, member, fields, ready, directory
    client.destroy()
    peer.close()
    stop_nodes(processes)


def _transform(parent: str, child: str, pose_mm: np.ndarray, stamp: Time) -> TransformStamped:
    item = TransformStamped()
    item.header.frame_id, item.child_frame_id, item.header.stamp = parent, child, stamp
    t, r = item.transform.translation, item.transform.rotation
    t.x, t.y, t.z = (float(v) for v in pose_mm[:3, 3] * messages.M_PER_MM)
    r.x, r.y, r.z, r.w = (float(v) for v in matrix_quaternion(pose_mm[:3, :3]))
    return item


def _send_view(peer, scan, frame: str, sec: int, pose: str = "topic") -> None:
    """A cloud in frame ``frame`` stamped ``sec``; its true pose on scan/pose ("topic"), as a static transform on
    /tf_static ("tf"), or nowhere ("none")."""
    cloud = scan_cloud(scan, sec * 1_000_000_000)
    cloud.header.frame_id = frame
    if pose == "topic":
        peer.publishers["scan/pose"].publish(_transform("hood", frame, scan.true_transform, cloud.header.stamp))
    elif pose == "tf":
        peer.publishers["/tf_static"].publish(TFMessage(transforms=[
            _transform("hood", frame, scan.true_transform, cloud.header.stamp)]))
    peer.wait(lambda: False, 0.3)  # the pose first: the node looks it up when the cloud comes
    peer.publishers["scan/points"].publish(cloud)


def _goal(peer, client, part_id: str, views: int, timeout_s: float = 0.0, variant: str = ""):
    feedback = []
    goal = InspectPart.Goal(part_id=part_id, variant=variant, expected_views=views,
                            timeout=Duration(sec=int(timeout_s), nanosec=int((timeout_s % 1) * 1e9)))
    sent = client.send_goal_async(goal, feedback_callback=lambda m: feedback.append(m.feedback))
    assert peer.wait(sent.done, 30.0)
    handle = sent.result()
    assert handle.accepted
    return handle, feedback


def _result(peer, handle, seconds: float = 120.0):
    future = handle.get_result_async()
    assert peer.wait(future.done, seconds), "no result"
    return future.result()


def test_goal_feedback_and_result_of_a_three_view_part(cell, coarse_hood):
    """Fails if the action does not fuse the three views (coverage above every single view's, feedback after each
    view with growing counts), if a view's pose from scan/pose or from TF is not used (the views would not overlap the
    part) or not reported, if the result's boundary state is not the estimator's answer for this part id, or if the
    estimate misses the scanned truth by more than 4 stated stds (or 0.05 mm)."""
    peer, client, _, scans, member, fields, ready, logs = cell
    assert ready, f"nodes or action server did not come up; logs in {logs}"
    handle, feedback = _goal(peer, client, "hood-0001", 3)
    _send_view(peer, scans[0], "camera_a", 101)
    _send_view(peer, scans[1], "camera_b", 102)
    _send_view(peer, scans[2], "camera_c", 103, pose="tf")
    response = _result(peer, handle)
    result = response.result
    assert response.status == GoalStatus.STATUS_SUCCEEDED and result.success, result.message
    assert result.part_id == "hood-0001" and result.views_used == 3 and not result.timed_out
    assert [f.views_received for f in feedback] == [1, 2, 3]
    assert feedback[0].coverage < feedback[1].coverage < feedback[2].coverage == pytest.approx(result.coverage)
    assert "pose from scan/pose" in result.view_reports[0] and "pose from tf" in result.view_reports[2]
    assert result.coverage > 0.8 and feedback[0].coverage < 0.7
    state = result.boundary_state
    assert state.part_id == "hood-0001" and result.boundary_correction.part_id == "hood-0001"
    assert any(f.part_id == "hood-0001" for f in fields)
    truth = dict(zip(coarse_hood.reduced.names, member.effective[0], strict=True))
    for name, value, std, lifted in zip(state.names, state.values, state.std_dev, state.lifted, strict=True):
        if lifted:
            continue
        error = abs(value * 1000 - truth[name])
        assert error <= max(4 * std * 1000, 0.005) and error < 0.05, (name, value * 1000, truth[name], std * 1000)


def test_timeout_with_fewer_views_and_a_view_without_pose(cell):
    """Fails if a view without a pose from any source is fused instead of refused by name, if the timeout does not
    close the part with the views it has and a result that says so (timed_out, 1 of 3 views, the refused one
    counted), or if the estimator's refusal of that field (too little coverage) is not in the result."""
    peer, client, _, scans, _, _, ready, _ = cell
    assert ready
    handle, feedback = _goal(peer, client, "hood-0002", 3, timeout_s=8.0)
    _send_view(peer, scans[0], "camera_d", 201)
    _send_view(peer, scans[1], "camera_nowhere", 202, pose="none")
    response = _result(peer, handle)
    result = response.result
    assert result.timed_out and result.views_used == 1 and result.views_refused == 1, result.message
    assert result.message.startswith("timeout: 1 of 3 view(s) fused")
    # one partial view covers about half the skin: the estimator refuses it, and the result says why at once
    assert not result.success and "the estimator refused it" in result.message, result.message
    refused = [f.last_view for f in feedback if f.views_refused]
    assert refused and "camera_nowhere" in refused[0] and "no pose" in refused[0], refused


def test_cancel_and_close_part(cell):
    """Fails if a canceled inspection does not end CANCELED, or if ClosePart does not close an open part early with
    the views received so far (and refuses when no part is open)."""
    peer, client, close, scans, _, _, ready, _ = cell
    assert ready
    handle, _ = _goal(peer, client, "hood-0003", 3)
    cancel = handle.cancel_goal_async()
    assert peer.wait(cancel.done, 30.0)
    response = _result(peer, handle)
    assert response.status == GoalStatus.STATUS_CANCELED and response.result.message.startswith("canceled")

    handle, feedback = _goal(peer, client, "hood-0004", 5)
    _send_view(peer, scans[0], "camera_e", 401)
    _send_view(peer, scans[1], "camera_f", 402)
    assert peer.wait(lambda: len(feedback) >= 2, 60.0)
    answer = close.call_async(ClosePart.Request(part_id="hood-0004"))
    assert peer.wait(answer.done, 30.0) and answer.result().success, answer.result().message
    result = _result(peer, handle).result
    assert result.success and result.views_used == 2 and result.message.startswith("closed by ClosePart"), \
        result.message
    again = close.call_async(ClosePart.Request())
    assert peer.wait(again.done, 30.0) and not again.result().success


def _diagnostic(peer, stamp_sec: int) -> dict[str, str] | None:
    """Key-values of the scan node's diagnostic about the cloud stamped ``stamp_sec``."""
    for array in peer.diagnostics:
        for status in array.status:
            values = {kv.key: kv.value for kv in status.values}
            if status.name.endswith("_scan") and values.get("stamp") == f"{stamp_sec}.000000000":
                return values
    return None


def test_a_lone_cloud_outside_an_inspection_uses_its_pose_and_says_which(cell):
    """Fails if, without a goal, a cloud is not one field of its own (part id from its stamp) placed by its pose on
    scan/pose (without the pose the partial view in the scanner frame would not overlap the part and be refused), or
    if /diagnostics does not name the pose source, for a lone cloud and for an inspection's view."""
    peer, _, _, scans, _, fields, ready, _ = cell
    assert ready
    _send_view(peer, scans[1], "camera_lone", 501)
    assert peer.wait(lambda: any(f.part_id == "stamp-501.000000000" for f in fields), 60.0)
    assert peer.wait(lambda: _diagnostic(peer, 501) is not None, 30.0)
    assert _diagnostic(peer, 501)["pose_source"].startswith("pose from scan/pose"), _diagnostic(peer, 501)
    assert _diagnostic(peer, 103)["pose_source"] == "tf"  # the first test's third view, inside its inspection


def test_a_goal_for_a_variant_not_served_is_rejected(cell):
    """Fails if the node accepts an inspection of a part variant whose bases it does not have (its views would be
    fused and estimated on another part's model)."""
    peer, client, _, _, _, _, ready, _ = cell
    assert ready
    sent = client.send_goal_async(InspectPart.Goal(part_id="rhd-0001", variant="RHD", expected_views=1))
    assert peer.wait(sent.done, 30.0)
    assert not sent.result().accepted


def _inspect(peer, client, part_id: str, scans, first_sec: int, variant: str = ""):
    """One inspection of the views ``scans`` (poses on scan/pose), stamped first_sec, first_sec + 1, ..."""
    handle, _ = _goal(peer, client, part_id, len(scans), variant=variant)
    for k, scan in enumerate(scans):
        _send_view(peer, scan, f"camera_{part_id}_{k}", first_sec + k)
    return _result(peer, handle).result


def test_the_nodes_state_the_same_std_as_the_core_path_for_a_multi_view_part(cell, coarse_hood):
    """Fails if the boundary state's std of a three-view part, through the scan node's fusion, the DisplacementField
    message and the estimator node, differs by more than 1 % from the std the core path states for the same views
    fused in this process (fuse_views, estimate_field): e.g. when the message drops the views' registration errors
    and the estimator falls back to their one-pose summary, which on this part is 5 % or more larger for at least
    one parameter (checked here, so the comparison can tell the two apart)."""
    from hood_decomp.core.loop.scan_skin import prepared_scan_skin
    from hood_decomp.core.method.bases import estimate_field
    from hood_decomp.core.scan.fusion import ScanView, fuse_views
    from hood_decomp.core.scan.scan_field import ScanFieldEstimator

    peer, client, _, scans, _, _, ready, _ = cell
    assert ready
    result = _inspect(peer, client, "hood-0017", scans, 1701)
    assert result.success and result.views_used == 3, result.message
    views = [ScanView(s.points, s.true_transform, s.markers, s.markers_nominal, name=f"view {k}", pose_source="file")
             for k, s in enumerate(scans)]
    # the preparation the nodes read from the bases file (its measured bias correlation), not a bare skin's fallback
    estimator = ScanFieldEstimator().fit(coarse_hood.skin, prepared=prepared_scan_skin(coarse_hood.bases))
    fused = fuse_views(coarse_hood.skin, views, estimator=estimator).field
    assert len(fused.errors.view_poses) == 3
    core = estimate_field(coarse_hood.bases, fused)
    one_pose = estimate_field(coarse_hood.bases, dataclasses.replace(
        fused, error_model=dataclasses.replace(fused.errors, view_poses=())))
    assert np.max(one_pose.std / core.std) > 1.05, one_pose.std / core.std
    state = result.boundary_state
    assert tuple(state.names) == core.names
    np.testing.assert_allclose(np.asarray(state.std_dev) * 1000, core.std, rtol=0.01)


def test_a_zone_out_of_tolerance_is_nok_with_its_worst_deviation(cell, zoned, coarse_hood):
    """Fails if the zone around the part's largest deviation (limits half of it) is not NOK, if its worst deviation
    differs from the one of the scanned FE field over the zone's nodes by more than 0.03 mm (scan noise 0.02 mm per
    point, smoothed) or its node lies more than one zone half-width away, if the zone within +-5 mm is not OK, or if
    zones_ok, the limits (m) or the coverage are not carried to the result."""
    peer, client, _, scans, _, _, ready, _ = cell
    assert ready
    result = _inspect(peer, client, "hood-0201", scans, 601)
    assert result.success, result.message
    corner, centre = result.zones
    assert (corner.name, centre.name) == ("lock_corner", "centre") and not result.zones_ok
    zone = zoned.zones[0]
    truth = zoned.truth[zone.nodes]
    excess = np.maximum(zone.lower_mm - truth, truth - zone.upper_mm)
    worst = int(np.argmax(excess))
    assert not corner.ok and "zone lock_corner NOK" in result.message, result.message
    assert abs(corner.worst_deviation * 1000 - truth[worst]) < 0.03, (corner.worst_deviation * 1000, truth[worst])
    distance = np.linalg.norm(coarse_hood.skin.points[corner.worst_node] - coarse_hood.skin.points[zone.nodes[worst]])
    assert distance < ZONE_HALF_WIDTH_MM, distance
    assert corner.upper == pytest.approx(zone.upper_mm / 1000) and corner.lower == pytest.approx(zone.lower_mm / 1000)
    assert corner.coverage > 0.5 and centre.ok and centre.coverage > 0.5
    assert abs(centre.worst_deviation * 1000) < 5.0


def test_a_move_applied_at_half_the_correction_is_named_partial(cell, coarse_hood):
    """Fails if the second inspection of a part, scanned after every applicable boundary was moved by half of the
    correction the first inspection sent, does not carry the estimator's verification in the action result with the
    moved boundaries PARTIAL, their measured change within 4 stated stds of half the correction and the slip named
    in the result's message; or if the first inspection carries a verification (there was no earlier correction)."""
    peer, client, _, scans, _, _, ready, _ = cell
    assert ready
    first = _inspect(peer, client, "hood-0301", scans, 701)
    assert first.success and not first.verification.names, first.message
    sent = first.boundary_correction
    assert all(sent.applicable[sent.names.index(name)] for name in TRUTH), sent.reason
    moved = dict(TRUTH)
    for name, correction, applicable in zip(sent.names, sent.corrections, sent.applicable, strict=True):
        if applicable:
            moved[name] = moved.get(name, 0.0) + 0.5 * correction * 1000
    _, after = scanned_part(coarse_hood, moved, 50, marker_noise_mm=0.01, n_holes=0)
    second = _inspect(peer, client, "hood-0301", after, 711)
    assert second.success, second.message
    verification = second.verification
    assert verification.part_id == "hood-0301" and list(verification.names) == list(sent.names)
    outcomes = dict(zip(verification.names, verification.outcome, strict=True))
    for name in TRUTH:
        k = verification.names.index(name)
        assert outcomes[name] == verification.PARTIAL, (name, outcomes[name], verification.summary)
        predicted, measured, std = verification.predicted[k], verification.measured[k], verification.std_dev[k]
        assert predicted == pytest.approx(sent.corrections[k])
        assert abs(measured - 0.5 * predicted) <= max(4 * std, 1e-5), (name, measured, predicted, std)
    assert not verification.all_achieved and "PARTIAL" in second.message, second.message


def test_two_variants_are_served_by_one_node_selected_by_the_goal(cell, zoned, coarse_hood):
    """Fails if the goal's variant does not select that variant's bases for fusion, estimation and zones (the result
    would carry the default model's id and zones), or if a part within every zone's limits is not zones_ok."""
    peer, client, _, scans, _, _, ready, _ = cell
    assert ready
    result = _inspect(peer, client, "h20-0001", scans, 801, variant="H20")
    assert result.success and result.variant == "H20", result.message
    assert result.model_id == zoned.h20_model_id != coarse_hood.bases.model_id
    assert result.boundary_state.model_id == zoned.h20_model_id
    assert [z.name for z in result.zones] == ["whole"] and result.zones_ok and result.zones[0].coverage > 0.8


def _scan_status(peer, stamp_sec: int):
    """The scan node's DiagnosticStatus about the cloud stamped ``stamp_sec`` (None before it came)."""
    return next((status for array in peer.diagnostics for status in array.status if status.name.endswith("_scan")
                 and any(kv.key == "stamp" and kv.value == f"{stamp_sec}.000000000" for kv in status.values)), None)


def _set_marker_std(peer, value) -> tuple[bool, str]:
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    request = SetParameters.Request(parameters=[Parameter("marker_std_mm", value=value).to_parameter_msg()])
    result = peer.call("/hood_decomp_scan/set_parameters", SetParameters, request, 30.0).results[0]
    return result.successful, result.reason


def test_a_stated_marker_noise_the_markers_reject_is_warned_and_not_used(cell):
    """Fails if the scan node uses its marker_std_mm parameter without checking it against the cloud's marker
    residual: stated 10 times below the synthetic scanner's marker noise (0.001 against 0.01 mm), a lone cloud's
    diagnostic must be a WARN saying "too small" and the published field's pose covariance the one of the
    residual's estimate (the stated value's is 100 times smaller); stated right (0.01 mm), an OK diagnostic and the
    stated value's covariance. Stated 1.4 times too small (0.0072 mm), two clouds each pass their own check (p 0.0016
    and 0.021) but the second must be a WARN for "the last 2 clouds" (pooled p 0.00014): fails if the node does not
    pool its clouds' residuals. The parameter callback refuses NaN and negative values. Truth: the scanner's marker
    noise and the nominal centres of the markers the view saw."""
    from hood_decomp.core.scan.registration import marker_pose_covariance

    peer, _, _, scans, _, fields, ready, _ = cell
    assert ready
    scan = scans[1]
    try:
        assert not _set_marker_std(peer, float("nan"))[0] and not _set_marker_std(peer, -0.01)[0]
        for sec, stated in ((611, 0.001), (612, 0.01)):
            assert _set_marker_std(peer, stated) == (True, "")
            _send_view(peer, scan, f"camera_marker_{sec}", sec)
            assert peer.wait(lambda sec=sec: _scan_status(peer, sec) is not None and any(
                f.part_id == f"stamp-{sec}.000000000" for f in fields), 60.0)
            status = _scan_status(peer, sec)
            values = {kv.key: kv.value for kv in status.values}
            assert values["registration"].startswith("markers"), values
            field = messages.msg_to_field(next(f for f in fields if f.part_id == f"stamp-{sec}.000000000"))
            used = float(values["marker_std_used_mm"])
            if stated == 0.001:
                assert status.level == DiagnosticStatus.WARN and "too small" in status.message, status.message
                assert used == float(values["marker_std_estimated_mm"]) > 0.005, values
            else:
                assert status.level == DiagnosticStatus.OK, status.message
                assert used == stated
            expected = marker_pose_covariance(scan.markers_nominal, used)[0]
            np.testing.assert_allclose(field.errors.pose_covariance, expected, rtol=2e-3,
                                       atol=1e-9 * np.abs(expected).max())
        assert _set_marker_std(peer, 0.0072) == (True, "")
        for sec, view, level in ((613, scans[1], DiagnosticStatus.OK), (614, scans[2], DiagnosticStatus.WARN)):
            _send_view(peer, view, f"camera_marker_{sec}", sec)
            assert peer.wait(lambda sec=sec: _scan_status(peer, sec) is not None, 60.0)
            status = _scan_status(peer, sec)
            assert status.level == level, status.message
        assert "the last 2 clouds" in status.message and "too small" in status.message, status.message
    finally:
        _set_marker_std(peer, 0.0)
