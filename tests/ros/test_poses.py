"""Pose sources of the scan node (hood_decomp.ros.poses): the TF buffer math against an analytic robot motion, and the
package's own /tf listener, scan/pose and the parameter fallback on the real middleware."""

from __future__ import annotations

import numpy as np
import pytest

from hood_decomp.ros.poses import PoseSources, TransformBuffer, matrix_quaternion, quaternion_matrix, slerp

OMEGA = 1.7  # rad/s about the tool axis: large enough that normalised linear interpolation is visibly wrong
VELOCITY = np.array([0.2, -0.1, 0.05])  # m/s


def rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def rigid(rotation: np.ndarray, translation) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    return matrix


AXIS = np.array([0.3, -0.2, 1.0])
PART_FROM_BASE = rigid(rot([0, 0, 1], 0.4), [1.5, -0.2, 0.0])  # static: the part's fixture in the robot base
FLANGE_FROM_CAMERA = rigid(rot([1, 0, 0], np.pi), [0.0, 0.05, 0.12])  # static: hand-eye calibration


def base_from_flange(t: float) -> np.ndarray:
    """The robot moving at constant angular rate about a fixed axis and at constant velocity: exactly what linear
    translation and slerp reproduce between two samples."""
    return rigid(rot(AXIS, OMEGA * t) @ rot([0, 1, 0], 0.3), np.array([0.4, 0.1, 0.9]) + VELOCITY * t)


def analytic(t: float) -> np.ndarray:
    """part <- camera at t."""
    return PART_FROM_BASE @ base_from_flange(t) @ FLANGE_FROM_CAMERA


def fill(buffer: TransformBuffer, times: list[float]) -> None:
    def add(parent, child, matrix, t, static):
        buffer.add(parent, child, round(t * 1e9), matrix[:3, 3], matrix_quaternion(matrix[:3, :3]), static)

    add("hood", "base", PART_FROM_BASE, 0.0, True)
    add("flange", "camera", FLANGE_FROM_CAMERA, 0.0, True)
    for t in times:
        add("base", "flange", base_from_flange(t), t, False)


def test_chain_lookup_interpolates_like_the_analytic_motion():
    """Fails if the buffer interpolates the rotation other than by slerp (normalised linear interpolation misses by
    ~0.03 rad at mid-interval for 1.0 rad between samples), the translation other than linearly, chains the frames in
    the wrong order, or inverts the direction of a lookup (camera <- hood must be the inverse)."""
    buffer = TransformBuffer()
    fill(buffer, [10.0, 10.6, 11.2])
    for t in (10.0, 10.13, 10.3, 10.6, 10.97):
        got = buffer.lookup("hood", "camera", round(t * 1e9))
        np.testing.assert_allclose(got, analytic(t), atol=1e-9)
        np.testing.assert_allclose(buffer.lookup("camera", "hood", round(t * 1e9)), np.linalg.inv(analytic(t)),
                                   atol=1e-9)
    # a lookup between siblings goes through their common ancestor
    np.testing.assert_allclose(buffer.lookup("base", "camera", int(10.3e9)),
                               base_from_flange(10.3) @ FLANGE_FROM_CAMERA, atol=1e-9)


def test_slerp_and_quaternions_against_closed_forms():
    """Fails if slerp leaves the great circle (angle not proportional to the fraction), takes the long way round for
    quaternions of opposite sign, or the quaternion <-> matrix conversions disagree with Rodrigues' formula."""
    for angle in (0.0, 1e-7, 0.5, 3.0):
        matrix = rot(AXIS, angle)
        np.testing.assert_allclose(quaternion_matrix(matrix_quaternion(matrix)), matrix, atol=1e-12)
    q0, q1 = matrix_quaternion(np.eye(3)), matrix_quaternion(rot(AXIS, 2.0))
    np.testing.assert_allclose(quaternion_matrix(slerp(q0, q1, 0.25)), rot(AXIS, 0.5), atol=1e-12)
    np.testing.assert_allclose(quaternion_matrix(slerp(q0, -q1, 0.25)), rot(AXIS, 0.5), atol=1e-12)


def test_lookups_outside_the_data_are_refused_with_the_reason():
    """Fails if the buffer extrapolates past its newest transform when not allowed to, allows more than the stated
    extrapolation, or a missing or unconnected frame is not named."""
    buffer = TransformBuffer()
    fill(buffer, [10.0, 10.5])
    with pytest.raises(LookupError, match="after the newest"):
        buffer.lookup("hood", "camera", int(10.6e9))
    with pytest.raises(LookupError, match="'laser' is not in the transform tree"):
        buffer.lookup("hood", "laser", int(10.2e9))
    buffer.add("world", "other", 0, np.zeros(3), np.array([0, 0, 0, 1.0]), static=True)
    with pytest.raises(LookupError, match="not connected"):
        buffer.lookup("hood", "other", int(10.2e9))
    tolerant = TransformBuffer(max_extrapolation_s=0.2)
    fill(tolerant, [10.0, 10.5])
    np.testing.assert_allclose(tolerant.lookup("hood", "camera", int(10.6e9)), analytic(10.5), atol=1e-9)
    with pytest.raises(LookupError):
        tolerant.lookup("hood", "camera", int(10.8e9))


def test_pose_sources_fall_back_in_order():
    """Fails if a later source is used while an earlier one has the pose, if the translation is not turned from m
    into mm, or if a cloud without any source does not fall back to the parameter (or, without one, the part frame)
    with each source's reason kept."""
    def have(matrix):
        return lambda target, source, stamp: matrix

    def missing(target, source, stamp):
        raise LookupError("no data")

    pose = analytic(0.0)
    first = PoseSources([("tf", have(pose)), ("scan/pose", have(np.eye(4)))]).resolve("hood", "camera", None)
    assert first.source == "tf"
    np.testing.assert_allclose(first.pose_mm[:3, 3], 1000 * pose[:3, 3])
    second = PoseSources([("tf", missing), ("scan/pose", have(pose))]).resolve("hood", "camera", None)
    assert second.source == "scan/pose" and second.skipped == ("tf: no data",)
    parameter = np.eye(4)
    parameter[:3, 3] = [1.0, 2.0, 3.0]
    third = PoseSources([("tf", missing)]).resolve("hood", "camera", None, parameter)
    assert third.source == "parameter" and third.pose_mm is parameter and "tf: no data" in third.report
    fourth = PoseSources([("tf", missing)]).resolve("hood", "camera", None)
    assert fourth.source == "part frame" and fourth.pose_mm is None


@pytest.mark.ros
def test_own_listener_reads_tf_and_tf_static_from_a_real_publisher():
    """A real rclpy publisher of /tf_static (transient local, published before the listener exists) and /tf, and the
    package's listener in another context. Fails if the latched static transforms are missed, the TFMessage type does
    not match a TF publisher's, the stamps are read wrongly (the interpolated pose at the cloud stamp must equal the
    analytic one), or a scan/pose message is not found by its child frame and stamp."""
    from tests.required import require_import

    require_import("tf2_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import TransformStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage

    from hood_decomp.ros.participant import Participant
    from hood_decomp.ros.poses import PoseTopic, TfListener

    def message(parent, child, matrix, t):
        item = TransformStamped()
        item.header.frame_id, item.child_frame_id = parent, child
        item.header.stamp = Time(sec=int(t), nanosec=round((t - int(t)) * 1e9))
        q = matrix_quaternion(matrix[:3, :3])
        tr, rr = item.transform.translation, item.transform.rotation
        tr.x, tr.y, tr.z = (float(v) for v in matrix[:3, 3])
        rr.x, rr.y, rr.z, rr.w = (float(v) for v in q)
        return item

    with Participant("tf_publisher") as robot, Participant("tf_listener") as cell:
        latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        static_pub = robot.node.create_publisher(TFMessage, "/tf_static", latched)
        static_pub.publish(TFMessage(transforms=[message("hood", "base", PART_FROM_BASE, 0.0),
                                                 message("flange", "camera", FLANGE_FROM_CAMERA, 0.0)]))
        dynamic_pub = robot.node.create_publisher(TFMessage, "/tf", 100)
        pose_pub = robot.publisher("scan/pose", TransformStamped)
        listener = TfListener(cell.node, TransformBuffer())
        topic = PoseTopic(cell.node)
        assert cell.wait(lambda: dynamic_pub.get_subscription_count() >= 1
                         and pose_pub.get_subscription_count() >= 1, 30.0)
        for t in (20.0, 20.25, 20.5):
            dynamic_pub.publish(TFMessage(transforms=[message("base", "flange", base_from_flange(t), t)]))
        pose_pub.publish(message("hood", "camera", analytic(20.3), 20.3))
        stamp = Time(sec=20, nanosec=300_000_000)

        def ready() -> bool:
            robot.executor.spin_once(timeout_sec=0.0)
            try:
                listener.lookup("hood", "camera", stamp)
                topic.lookup("hood", "camera", stamp)
            except LookupError:
                return False
            return True

        assert cell.wait(ready, 30.0), "no transform arrived"
        np.testing.assert_allclose(listener.lookup("hood", "camera", stamp), analytic(20.3), atol=1e-7)
        np.testing.assert_allclose(topic.lookup("hood", "camera", stamp), analytic(20.3), atol=1e-7)
        with pytest.raises(LookupError, match="not the part frame"):
            topic.lookup("world", "camera", stamp)


def test_a_lookup_waits_for_a_transform_still_on_its_way():
    """Fails if a lookup at a stamp newer than the buffer's newest transform does not wait for the transform that a
    listener thread adds a moment later (a cloud arrives before the TF after its stamp), or if it waits for data
    that cannot come (an unknown frame must fail at once)."""
    import threading
    import time

    from hood_decomp.ros.poses import _waiting

    buffer = TransformBuffer()
    fill(buffer, [10.0])
    later = base_from_flange(10.5)
    thread = threading.Timer(0.1, lambda: buffer.add("base", "flange", int(10.5e9), later[:3, 3],
                                                     matrix_quaternion(later[:3, :3])))
    thread.start()
    got = _waiting(lambda: buffer.lookup("hood", "camera", int(10.2e9)), 2.0,
                   lambda error: "after the newest" in str(error))
    thread.join()
    np.testing.assert_allclose(got, analytic(10.2), atol=1e-9)
    start = time.monotonic()
    with pytest.raises(LookupError, match="not in the transform tree"):
        _waiting(lambda: buffer.lookup("hood", "laser", int(10.2e9)), 2.0,
                 lambda error: "after the newest" in str(error))
    assert time.monotonic() - start < 1.0
