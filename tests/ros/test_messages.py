"""The project messages: built, importable from the sourced environment, serialisable by rclpy and decodable by an
independent CDR implementation (rosbags), and converted to and from the core dataclasses with mm <-> m."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
from hood_decomp_msgs import msg as hd_msg
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from std_msgs.msg import Header

from hood_decomp.core.types import (
    BoundaryCorrection,
    Decomposition,
    DisplacementField,
    EffectContribution,
    FieldErrorModel,
    ModelCheck,
    ParameterEstimate,
)
from hood_decomp.ros import messages
from hood_decomp.ros.pointcloud import cloud_channel, cloud_to_xyz, xyz_to_cloud
from tests.toy_models import make_skin

MSG_DIR = pathlib.Path(__file__).parents[2] / "ros2_ws/src/hood_decomp_msgs/msg"
NAMES = ["DisplacementField", "BoundaryState", "BoundaryCorrection", "EffectField", "EffectFields", "MoveVerification",
         "ZoneVerdict"]


@pytest.fixture(scope="module")
def typestore():
    store = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for name in NAMES:
        types.update(get_types_from_msg((MSG_DIR / f"{name}.msg").read_text(), f"hood_decomp_msgs/msg/{name}"))
    store.register(types)
    return store


def rosbags_decode(typestore, message) -> object:
    """Serialise with rclpy (Fast CDR) and decode with rosbags' own CDR reader."""
    name = f"hood_decomp_msgs/msg/{type(message).__name__}"
    return typestore.deserialize_cdr(bytes(serialize_message(message)), name)


def test_every_message_is_generated():
    for name in NAMES:
        cls = getattr(hd_msg, name)
        assert deserialize_message(serialize_message(cls()), cls) == cls()


def test_inspect_part_action_and_close_part_service_are_generated():
    """Fails if the action or service is not generated (rosidl without action_msgs/service_msgs) or its parts do not
    carry what the cell controller reads: the goal's part id and view count, the result's part id, state, correction,
    verification and zone verdicts."""
    from hood_decomp_msgs.action import InspectPart
    from hood_decomp_msgs.srv import ClosePart

    goal = InspectPart.Goal(part_id="P-17", variant="LHD", expected_views=4)
    goal.timeout.sec = 30
    assert deserialize_message(serialize_message(goal), InspectPart.Goal) == goal
    result = InspectPart.Result(part_id="P-17", views_used=3, timed_out=True, zones=[hd_msg.ZoneVerdict(name="z")])
    result.boundary_state.part_id = result.boundary_correction.part_id = "P-17"
    result.verification.outcome = [hd_msg.MoveVerification.PARTIAL]
    back = deserialize_message(serialize_message(result), InspectPart.Result)
    assert back == result and back.boundary_correction.part_id == "P-17" and back.zones[0].name == "z"
    feedback = InspectPart.Feedback(views_received=2, coverage=0.5)
    assert deserialize_message(serialize_message(feedback), InspectPart.Feedback) == feedback
    assert ClosePart.Request(part_id="P-17").part_id == "P-17" and not ClosePart.Response().success


def test_part_id_is_kept_or_made_from_the_stamp():
    """Fails if a given part id is replaced, or a missing one is not made, or made differently for two messages of
    the same stamp (the estimator and the decomposition node must agree on it), or the same for different stamps."""
    from builtin_interfaces.msg import Time

    given = hd_msg.DisplacementField(part_id="P-1")
    assert messages.part_id_of(given) == "P-1"
    a = hd_msg.DisplacementField(header=Header(stamp=Time(sec=12, nanosec=5)))
    b = hd_msg.BoundaryState(header=Header(stamp=Time(sec=12, nanosec=5)))
    c = hd_msg.DisplacementField(header=Header(stamp=Time(sec=12, nanosec=6)))
    assert messages.part_id_of(a) == messages.part_id_of(b) == "stamp-12.000000005"
    assert messages.part_id_of(c) != messages.part_id_of(a)


def test_displacement_field_mm_to_m(typestore):
    values = np.array([1.5, -0.25, np.nan, 0.0])
    field = DisplacementField(model_id="abc123", normal_displacement=values, coverage=0.75, noise_rms=0.02)
    msg = messages.field_to_msg(field, Header(frame_id="part"), "P-7")
    decoded = rosbags_decode(typestore, msg)
    np.testing.assert_allclose(decoded.normal_displacement, [0.0015, -0.00025, np.nan, 0.0], rtol=1e-7)
    assert decoded.model_id == "abc123" and decoded.header.frame_id == "part" and decoded.part_id == "P-7"
    assert decoded.noise_rms == pytest.approx(2e-5)
    back = messages.msg_to_field(msg)
    np.testing.assert_allclose(back.normal_displacement, values, rtol=1e-7, atol=1e-9)
    assert back.coverage == 0.75 and back.noise_rms == pytest.approx(0.02)



def test_a_fields_3d_displacement_travels_in_metres_and_a_wrong_length_is_named(typestore):
    """A simulated field's 3D displacement (N, 3) mm comes back (mm, NaN rows kept) through rclpy and rosbags' CDR
    reader; a field without one (a scan) sends none and comes back without; 3 N - 1 values are a FieldError."""
    from hood_decomp.errors import FieldError

    vectors = np.array([[1.5, -0.25, 0.125], [np.nan, np.nan, np.nan], [0.0, 2.0, -3.0], [1e-3, 0.0, 0.5]])
    normal = np.array([0.125, np.nan, -3.0, 0.5])  # the normal part for normals (0, 0, 1)
    field = DisplacementField("abc123", normal, 0.75, np.nan, displacement=vectors)
    msg = messages.field_to_msg(field, Header(), "P-21")
    decoded = rosbags_decode(typestore, msg)
    np.testing.assert_allclose(decoded.displacement_3d, vectors.ravel() / 1000.0, rtol=1e-7)
    for sent in (msg, decoded):
        back = messages.msg_to_field(sent)
        np.testing.assert_allclose(back.displacement, vectors, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(back.checked_displacement(np.tile([0.0, 0.0, 1.0], (4, 1))), vectors, rtol=1e-7)
    plain = messages.field_to_msg(DisplacementField("abc123", normal, 0.75, np.nan), Header(), "P-21")
    assert len(plain.displacement_3d) == 0 and messages.msg_to_field(plain).displacement is None
    msg.displacement_3d = msg.displacement_3d[:-1]
    with pytest.raises(FieldError, match="displacement_3d must hold 3 N values"):
        messages.msg_to_field(msg)

def test_field_error_model_travels_in_metres(typestore):
    """Fails if the error model (node std, correlation, pose covariance with its mixed rad/length units, pose centre,
    lengths) is not converted mm <-> m on the way through the message, or a field without one does not come back as
    "none"."""
    cov = np.diag([1e-8, 2e-8, 3e-8, 0.01, 0.02, 0.03])  # rad^2 and mm^2
    cov[0, 3] = cov[3, 0] = 1e-5  # rad mm
    errors = FieldErrorModel("scan", np.array([0.002, np.nan, 0.003, 0.001]), np.array([11.0, 1.0, 12.0, 10.0]),
                             12.5, cov, np.array([100.0, 200.0, 300.0]), 300.0, bias_variance_floor=4e-5)
    field = DisplacementField("abc", np.array([1.5, np.nan, 0.0, 0.2]), 0.75, 0.02, errors)
    msg = messages.field_to_msg(field, Header(), "P-1")
    decoded = rosbags_decode(typestore, msg)
    assert decoded.error_model == "scan" and decoded.correlation_length == pytest.approx(0.0125)
    np.testing.assert_allclose(decoded.node_std, [2e-6, np.nan, 3e-6, 1e-6], rtol=1e-6)
    np.testing.assert_allclose(np.reshape(decoded.pose_covariance, (6, 6))[3, 3], 0.01e-6)
    np.testing.assert_allclose(np.reshape(decoded.pose_covariance, (6, 6))[0, 3], 1e-8)
    np.testing.assert_allclose(decoded.pose_center, [0.1, 0.2, 0.3])
    assert decoded.bias_variance_floor == pytest.approx(4e-11, rel=1e-12)  # mm^2 -> m^2
    back = messages.msg_to_field(msg).error_model
    assert back.bias_variance_floor == pytest.approx(4e-5, rel=1e-12)
    np.testing.assert_allclose(back.pose_covariance, cov, rtol=1e-12)
    np.testing.assert_allclose(back.node_std, errors.node_std, rtol=1e-6)
    np.testing.assert_allclose(back.correlation, errors.correlation, rtol=1e-6)
    assert back.bias_correlation == 300.0 and back.correlation_length_mm == pytest.approx(12.5)
    plain = messages.msg_to_field(messages.field_to_msg(DisplacementField("abc", np.zeros(4), 1.0, np.nan), Header(),
                                                                 "P-1"))
    assert plain.error_model.kind == "none"


def _two_view_field() -> tuple[DisplacementField, np.ndarray, np.ndarray]:
    """Two overlapping views of the toy skin, each with white node noise and its own registration covariance about
    its own centre, fused by fuse_fields; with the exact registration covariance of the fused node values (N, N),
    computed here by hand from its definition (sum over views of w_v J_v C_v J_v^T w_v, J the rigid-body modes),
    and that of the one-pose summary (all views' covariances summed about one centre, every node moved together)."""
    from hood_decomp.core.scan.fusion import fuse_fields

    skin = make_skin(12, 8)
    n = skin.n_nodes
    x = skin.points[:, 0]
    fields, covariances, centers, variances = [], [], [], []
    for v, (seen, noise) in enumerate(((x <= 1000.0, 0.02), (x >= 500.0, 0.03))):
        rng = np.random.default_rng(v)
        root = rng.normal(size=(6, 6)) * np.array([2e-5, 2e-5, 2e-5, 0.02, 0.02, 0.02])[:, None]
        covariances.append(root @ root.T)
        centers.append(skin.points[seen].mean(axis=0))
        std = np.where(seen, noise, np.nan)
        errors = FieldErrorModel("scan", std, np.ones(n), 0.0, covariances[-1], centers[-1])
        fields.append(DisplacementField("toy", np.where(seen, 0.1 * v, np.nan), float(seen.mean()), noise, errors))
        variances.append(np.where(seen, noise**2, np.inf))
    fused = fuse_fields(fields, skin)

    def modes(center: np.ndarray) -> np.ndarray:  # (N, 6) normal motion per unit twist [omega, t] about center
        return np.hstack([np.cross(skin.points - center, skin.normals), skin.normals])

    # weights from each view's own node variance (noise + its registration at the node), by hand
    node_pose = [np.einsum("ij,jk,ik->i", modes(c), cov, modes(c)) for c, cov in zip(centers, covariances,
                                                                                     strict=True)]
    precision = np.array([1.0 / (s + p) for s, p in zip(variances, node_pose, strict=True)])
    weight = precision / precision.sum(axis=0)
    exact = sum(w[:, None] * modes(c) @ cov @ modes(c).T * w[None, :]
                for w, c, cov in zip(weight, centers, covariances, strict=True))
    common = np.mean(centers, axis=0)
    summary_modes = modes(common)
    summary = summary_modes @ fused.errors.pose_covariance @ summary_modes.T
    assert np.allclose(fused.errors.pose_center, common) and exact.shape == (n, n)
    return fused, exact, summary


def test_a_fused_field_keeps_each_views_registration_error_through_the_message(typestore):
    """Fails if the message drops the views' registration errors of a fused field (the estimator node would see the
    one-pose summary, the old conservative behaviour: here 5 % or more off on the node variances), if their units
    (rad, mm -> m) or layout (V x 39, V x N) are wrong, or if the registration covariance of the node values
    after the round trip (serialised by rclpy, decoded also by rosbags' independent CDR reader) differs from the one
    computed by hand from the views' covariances and fusion weights by more than 1e-5 (relative)."""
    from rclpy.serialization import deserialize_message, serialize_message

    fused, exact, summary = _two_view_field()
    n = fused.normal_displacement.shape[0]
    skin = make_skin(12, 8)
    msg = messages.field_to_msg(fused, Header(), "P-17")
    decoded = rosbags_decode(typestore, msg)
    assert (len(decoded.view_poses), len(decoded.view_weight)) == (78, 2 * n)
    for source in (deserialize_message(serialize_message(msg), hd_msg.DisplacementField), decoded):
        back = messages.msg_to_field(source).error_model
        back.validate(n)
        m = back.registration_modes(skin.points, skin.normals)
        scale = np.abs(exact).max()
        np.testing.assert_allclose(m @ m.T, exact, rtol=0.0, atol=1e-5 * scale)
    node_exact, node_summary = np.diag(exact), np.diag(summary)
    assert np.max(np.abs(node_summary / node_exact - 1.0)) > 0.05  # what dropping the views would look like


def test_a_field_without_views_keeps_its_one_pose_and_bad_view_arrays_are_named(typestore):
    """Fails if a message without view arrays (one view, an older sender) does not come back with its one pose
    covariance as its registration error, or if view arrays of inconsistent lengths are accepted (or crash with
    anything but a FieldError naming the two fields). Also through rosbags' CDR reader: an empty float64[] after a
    4-byte length is padded by Fast CDR and not by rosbags, so a layout that puts one there does not decode."""
    from hood_decomp.errors import FieldError

    fused, _, summary = _two_view_field()
    skin = make_skin(12, 8)
    msg = messages.field_to_msg(fused, Header(), "P-17")
    msg.view_poses, msg.view_weight = [], []
    assert messages.msg_to_field(rosbags_decode(typestore, msg)).error_model.view_poses == ()
    back = messages.msg_to_field(msg).error_model
    assert back.view_poses == ()
    m = back.registration_modes(skin.points, skin.normals)
    np.testing.assert_allclose(m @ m.T, summary, rtol=0.0, atol=1e-9 * np.abs(summary).max())
    bad = messages.field_to_msg(fused, Header(), "P-17")
    bad.view_weight = bad.view_weight[:-1]
    with pytest.raises(FieldError, match="view_poses and view_weight must hold"):
        messages.msg_to_field(bad)


def _estimate() -> ParameterEstimate:
    return ParameterEstimate(
        model_id="m1", names=("HINGE_X", "BUFFER_L"), values=np.array([0.5, -0.2]), std=np.array([0.001, 0.002]),
        lower=np.array([-1.0, -1.0]), upper=np.array([1.0, 1.0]), lifted=np.array([False, True]),
        reconstruction=np.zeros(3), residual=np.zeros(3), residual_rms=0.01, residual_max=0.05, coverage=0.9,
        within_model=True, method="contact", covariance=np.array([[1e-6, -5e-7], [-5e-7, 4e-6]]),
        check=ModelCheck(3.0, 5, 800.0, 0.4, 0.01, True, 1.1, "error model", 900.0),
    )


def test_boundary_state_mm_to_m(typestore):
    msg = messages.estimate_to_msg(_estimate(), Header(), "P-2")
    decoded = rosbags_decode(typestore, msg)
    assert decoded.part_id == "P-2"
    np.testing.assert_allclose(decoded.values, [0.0005, -0.0002])
    np.testing.assert_allclose(decoded.std_dev, [1e-6, 2e-6])
    assert list(decoded.lifted) == [False, True] and decoded.residual_max == pytest.approx(5e-5)
    back = messages.msg_to_estimate(msg)
    np.testing.assert_allclose(back.values, [0.5, -0.2])
    np.testing.assert_allclose(back.upper, [1.0, 1.0])
    assert back.names == ("HINGE_X", "BUFFER_L") and back.reconstruction.shape == (0,)
    # the full covariance in m^2 and back, and the within-model test's p-value, alpha and noise level
    np.testing.assert_allclose(decoded.covariance, [1e-12, -5e-13, -5e-13, 4e-12])
    np.testing.assert_allclose(back.covariance, [[1e-6, -5e-7], [-5e-7, 4e-6]])
    assert back.check.p_value == 0.4 and back.check.alpha == 0.01 and back.check.noise_source == "error model"


def test_boundary_correction_mm_to_m(typestore):
    correction = BoundaryCorrection(model_id="m1", names=("LOCK_L", "HINGE_X"), corrections=np.array([-0.8, 0.1]),
                                    safe_to_apply=False, reason="coverage 0.30 below 0.60",
                                    std=np.array([0.002, 0.07]), applicable=np.array([True, False]),
                                    remaining=np.array([-0.3, 0.0]))
    decoded = rosbags_decode(typestore, messages.correction_to_msg(correction, Header(), "P-3"))
    assert decoded.part_id == "P-3"
    assert list(decoded.corrections) == pytest.approx([-0.0008, 0.0001])
    assert decoded.reason == "coverage 0.30 below 0.60"
    assert list(decoded.std_dev) == pytest.approx([2e-6, 7e-5]) and list(decoded.applicable) == [True, False]
    back = messages.msg_to_correction(messages.correction_to_msg(correction, Header(), "P-3"))
    assert back.corrections == pytest.approx([-0.8, 0.1]) and not back.safe_to_apply
    assert back.std == pytest.approx([0.002, 0.07]) and list(back.applicable) == [True, False]
    assert list(decoded.remaining) == pytest.approx([-0.0003, 0.0]) and back.remaining == pytest.approx([-0.3, 0.0])
    assert list(decoded.measured_effect) == [] and back.measured_effect is None


def test_measured_effect_flags_travel_in_state_and_correction(typestore):
    """Fails if the per-parameter measured-effect flag (a parameter without a boundary) is lost or shifted on its way
    through BoundaryState and BoundaryCorrection (as rosbags decodes a recorded message, and back to the core)."""
    import dataclasses

    estimate = dataclasses.replace(_estimate(), measured_effect=np.array([True, False]))
    decoded = rosbags_decode(typestore, messages.estimate_to_msg(estimate, Header(), "P-4"))
    assert list(decoded.measured_effect) == [True, False]
    back = messages.msg_to_estimate(messages.estimate_to_msg(estimate, Header(), "P-4"))
    assert list(back.measured_effect) == [True, False] and list(back.boundary) == [False, True]
    correction = BoundaryCorrection(model_id="m1", names=("measured_1", "HINGE_X"), corrections=np.array([0.0, 0.1]),
                                    safe_to_apply=True, reason="", measured_effect=np.array([True, False]))
    decoded = rosbags_decode(typestore, messages.correction_to_msg(correction, Header(), "P-4"))
    assert list(decoded.measured_effect) == [True, False]
    assert list(messages.msg_to_correction(messages.correction_to_msg(correction, Header(), "P-4"))
                .measured_effect) == [True, False]


def test_effect_fields_mm_to_m(typestore):
    effects = (
        EffectContribution("LOCK_L", ("LOCK_L",), np.array([1.0, 0.0]), np.array([1.0, 0.0]), 0.6),
        EffectContribution("LOCK_L & LOCK_R", ("LOCK_L", "LOCK_R"), np.array([0.0, 2.0]), np.array([0.0, 1.0]), 0.4),
    )
    decomposition = Decomposition("m1", effects, np.array([1.0, 2.0]), np.array([0.001, np.nan]), 0.0007)
    msg = messages.decomposition_to_msg(decomposition, Header(), "P-4")
    decoded = rosbags_decode(typestore, msg)
    assert decoded.part_id == "P-4"
    assert [e.name for e in decoded.effects] == ["LOCK_L", "LOCK_L & LOCK_R"]
    assert list(decoded.effects[1].parameters) == ["LOCK_L", "LOCK_R"]
    np.testing.assert_allclose(decoded.reconstruction, [0.001, 0.002], rtol=1e-7)
    back = messages.msg_to_decomposition(msg)
    np.testing.assert_allclose(back.effects[1].contribution, [0.0, 1.0])
    np.testing.assert_allclose(back.residual, [0.001, np.nan], rtol=1e-6)
    assert back.reconstruction_rms == pytest.approx(0.0007)


def _cloud(points_m: np.ndarray, ids: np.ndarray | None = None):
    return xyz_to_cloud(points_m, Header(), channels=None if ids is None else {"marker_id": ids})


def test_scan_cloud_to_mm_drops_no_return_points_and_takes_known_markers_out():
    points_m = np.array([[0.1, 0.2, 0.3], [np.nan, 0.0, 0.0], [0.4, 0.5, 0.6], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0],
                         [np.nan, 8.0, 9.0], [7.0, 8.0, 9.0]])
    ids = np.array([-1, -1, -1, 3, 9, 4, 4], dtype=float)  # marker 9 is not configured; one centre of 4 has no return
    nominal = {3: np.array([10.0, 20.0, 30.0]), 4: np.array([40.0, 50.0, 60.0])}
    surface, markers, markers_nominal = messages.scan_to_mm(_cloud(points_m, ids), "marker_id", nominal)
    np.testing.assert_allclose(surface, [[100.0, 200.0, 300.0], [400.0, 500.0, 600.0]], rtol=1e-6)
    np.testing.assert_allclose(markers, [[1000.0, 2000.0, 3000.0], [7000.0, 8000.0, 9000.0]], rtol=1e-6)
    np.testing.assert_array_equal(markers_nominal, [nominal[3], nominal[4]])
    # No marker configured (or no marker channel): every finite point is a surface point.
    surface, markers, markers_nominal = messages.scan_to_mm(_cloud(points_m, ids), "marker_id", {})
    assert surface.shape == (5, 3) and markers is None and markers_nominal is None
    assert messages.scan_to_mm(_cloud(points_m), "marker_id", nominal)[0].shape == (5, 3)
    # Nothing finite: the rows go on whole, so the core names the all-NaN scan.
    surface, _, _ = messages.scan_to_mm(_cloud(np.full((4, 3), np.nan)), "marker_id", nominal)
    assert surface.shape == (4, 3) and np.isnan(surface).all()


def test_skin_clouds_are_the_skin_in_metres_with_the_per_node_channels():
    skin = make_skin(6, 5)
    values = np.linspace(-1.0, 1.0, skin.n_nodes)
    values[3] = np.nan
    clouds = messages.SkinClouds(skin)
    header = Header(frame_id="hood")
    cloud = clouds.displacement(DisplacementField(skin.model_id, values, 0.9, 0.01), header)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "normal_displacement"] and cloud.header.frame_id == "hood"
    np.testing.assert_allclose(cloud_to_xyz(cloud), skin.points / 1000.0, rtol=1e-7)
    np.testing.assert_allclose(cloud_channel(cloud, "normal_displacement"), values / 1000.0, rtol=1e-6)
    effect = EffectContribution("LOCK_L & LOCK_R", ("LOCK_L", "LOCK_R"), values, np.full(skin.n_nodes, 0.25), 0.25)
    cloud = clouds.effects(Decomposition(skin.model_id, (effect,), values, values, 0.0), header)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "LOCK_L__LOCK_R"]
    np.testing.assert_array_equal(cloud_channel(cloud, "LOCK_L__LOCK_R"), 0.25)


def test_cell_calibration_parameters_mm_to_m_and_back():
    pose_mm = np.eye(4)
    pose_mm[:3, 3] = [1200.0, -35.5, 800.0]
    markers_mm = {"3": [10.0, 20.0, 30.0], "11": [-400.0, 0.0, 5.5]}
    pose, markers = messages.calibration_to_params(pose_mm, markers_mm)
    assert pose[3] == pytest.approx(1.2) and markers[:4] == pytest.approx([3.0, 0.01, 0.02, 0.03])
    back_pose, back_markers = messages.calibration_from_params(pose, markers)
    np.testing.assert_allclose(back_pose, pose_mm, rtol=1e-12)
    assert sorted(back_markers) == [3, 11]
    np.testing.assert_allclose(back_markers[11], markers_mm["11"], rtol=1e-12)
