"""Where each cloud's pose (part <- cloud frame, at the cloud's stamp) comes from, in order (DESIGN.md "Robotic cell"):

1. TF: ``part_frame`` <- the cloud's ``header.frame_id`` at the cloud's stamp, through ``tf2_ros`` where a full ROS
   install has it ("tf2_ros"), else through this module's own listener of ``/tf`` and ``/tf_static``
   (``tf2_msgs/TFMessage``; the workspace builds the type where no wheel has it) and :class:`TransformBuffer` ("tf");
2. a ``geometry_msgs/TransformStamped`` on ``scan/pose`` with the cloud's stamp (header.frame_id = part frame,
   child_frame_id = the cloud's frame) ("scan/pose");
3. the ``scanner_pose`` parameter, the fixed cell's calibration ("parameter"; "part frame" when it was left at the
   identity: the points are taken in the part frame, as a lone cloud always was).

:class:`TransformBuffer` is the TF math without ROS: a frame tree of static and time-stamped edges, each edge
interpolated between the two transforms around the requested time (linear translation, slerp rotation), chained
through the common ancestor; no extrapolation beyond ``max_extrapolation_s``. Transforms are (4, 4) in metres here;
the node turns them into mm (the ROS adapter layer is the only place of the conversion).
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: how long time-stamped transforms are kept (s); tf2's default cache is 10 s
CACHE_S = 10.0


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a quaternion (x, y, z, w) (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w), w >= 0, of a (3, 3) rotation (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.zeros(4)
        q[i] = s / 4
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    return q if q[3] >= 0 else -q


def slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (x, y, z, w) along the shorter arc."""
    q0, q1 = np.asarray(q0, float) / np.linalg.norm(q0), np.asarray(q1, float) / np.linalg.norm(q1)
    dot = float(q0 @ q1)
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: linear is exact to round-off and avoids 0 / 0
        q = q0 + fraction * (q1 - q0)
        return q / np.linalg.norm(q)
    angle = np.arccos(dot)
    return (np.sin((1 - fraction) * angle) * q0 + np.sin(fraction * angle) * q1) / np.sin(angle)


def transform_matrix(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """(4, 4) homogeneous transform from a translation (3,) and a quaternion (x, y, z, w)."""
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_matrix(quaternion)
    matrix[:3, 3] = translation
    return matrix


@dataclass
class _Edge:
    """One parent <- child edge: static (one transform) or a time series sorted by stamp (ns)."""

    parent: str
    static: np.ndarray | None = None
    stamps: list[int] = field(default_factory=list)
    translations: list[np.ndarray] = field(default_factory=list)
    quaternions: list[np.ndarray] = field(default_factory=list)


class TransformBuffer:
    """Parent <- child transforms over time, looked up along the frame tree at any stamp inside the data.

    ``add(parent, child, stamp_ns, translation, quaternion, static)``; ``lookup(target, source, stamp_ns)`` -> (4, 4)
    target <- source (x_target = T x_source). Raises LookupError naming the missing frame or the time gap.
    max_extrapolation_s: how far past the newest (or before the oldest) transform of an edge a lookup may reach, using
    that transform as it is (0: none, as tf2); cache_s: how long time-stamped transforms are kept.
    """

    def __init__(self, max_extrapolation_s: float = 0.0, cache_s: float = CACHE_S) -> None:
        self.max_extrapolation_s = max_extrapolation_s
        self.cache_s = cache_s
        self._edges: dict[str, _Edge] = {}
        self._lock = threading.Lock()  # a listener thread adds while a cloud's thread looks up

    def add(self, parent: str, child: str, stamp_ns: int, translation: np.ndarray, quaternion: np.ndarray,
            static: bool = False) -> None:
        with self._lock:
            self._add(parent, child, stamp_ns, translation, quaternion, static)

    def _add(self, parent: str, child: str, stamp_ns: int, translation: np.ndarray, quaternion: np.ndarray,
             static: bool) -> None:
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if not parent or not child or parent == child:
            raise ValueError(f"a transform needs two different frame names; got {parent!r} <- {child!r}")
        t, q = np.asarray(translation, float), np.asarray(quaternion, float)
        if t.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))) \
                or np.linalg.norm(q) < 1e-9:
            raise ValueError(f"transform {parent} <- {child}: translation must be 3 finite numbers and the rotation a "
                             "non-zero finite quaternion")
        edge = self._edges.get(child)
        if edge is None or edge.parent != parent:  # a frame has one parent: a new one replaces the old edge
            edge = self._edges[child] = _Edge(parent)
        if static:
            edge.static = transform_matrix(t, q)
            return
        i = bisect.bisect_left(edge.stamps, stamp_ns)
        if i < len(edge.stamps) and edge.stamps[i] == stamp_ns:
            edge.translations[i], edge.quaternions[i] = t, q / np.linalg.norm(q)
        else:
            edge.stamps.insert(i, stamp_ns)
            edge.translations.insert(i, t)
            edge.quaternions.insert(i, q / np.linalg.norm(q))
        oldest = edge.stamps[-1] - int(self.cache_s * 1e9)
        drop = bisect.bisect_left(edge.stamps, oldest)
        if drop:
            del edge.stamps[:drop], edge.translations[:drop], edge.quaternions[:drop]

    def frames(self) -> set[str]:
        return set(self._edges) | {edge.parent for edge in self._edges.values()}

    def _edge_at(self, child: str, stamp_ns: int) -> np.ndarray:
        edge = self._edges[child]
        if edge.static is not None:
            return edge.static
        stamps = edge.stamps
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return transform_matrix(edge.translations[i], edge.quaternions[i])
        if i == 0 or i == len(stamps):
            k = 0 if i == 0 else len(stamps) - 1
            gap = abs(stamp_ns - stamps[k]) / 1e9
            if gap <= self.max_extrapolation_s:
                return transform_matrix(edge.translations[k], edge.quaternions[k])
            side = "before the oldest" if i == 0 else "after the newest"
            raise LookupError(f"{edge.parent} <- {child} at {stamp_ns / 1e9:.3f} s: {gap:.3f} s {side} transform "
                              f"(extrapolation limit {self.max_extrapolation_s:g} s)")
        fraction = (stamp_ns - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        translation = (1 - fraction) * edge.translations[i - 1] + fraction * edge.translations[i]
        return transform_matrix(translation, slerp(edge.quaternions[i - 1], edge.quaternions[i], fraction))

    def _chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root."""
        chain, seen = [frame], {frame}
        while chain[-1] in self._edges:
            parent = self._edges[chain[-1]].parent
            if parent in seen:
                raise LookupError(f"the frame tree has a loop through {parent!r}")
            chain.append(parent)
            seen.add(parent)
        return chain

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """(4, 4) target <- source at ``stamp_ns`` (metres)."""
        with self._lock:
            return self._lookup(target, source, stamp_ns)

    def _lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.eye(4)
        known = self.frames()
        for frame in (target, source):
            if frame not in known:
                raise LookupError(f"frame {frame!r} is not in the transform tree (known: {sorted(known)[:10]})")
        up_source, up_target = self._chain(source), self._chain(target)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            raise LookupError(f"frames {target!r} and {source!r} are not connected")
        root_from_source = np.eye(4)
        for frame in up_source[: up_source.index(common)]:
            root_from_source = self._edge_at(frame, stamp_ns) @ root_from_source
        root_from_target = np.eye(4)
        for frame in up_target[: up_target.index(common)]:
            root_from_target = self._edge_at(frame, stamp_ns) @ root_from_target
        return np.linalg.inv(root_from_target) @ root_from_source


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def transform_msg_matrix(transform: Any) -> np.ndarray:
    """(4, 4) metres of a geometry_msgs/Transform."""
    t, r = transform.translation, transform.rotation
    return transform_matrix(np.array([t.x, t.y, t.z]), np.array([r.x, r.y, r.z, r.w]))


def _waiting(lookup: Callable[[], np.ndarray], wait_s: float, retry: Callable[[LookupError], bool]) -> np.ndarray:
    """``lookup()``, tried again for up to ``wait_s`` while it fails in a way ``retry`` says may pass (data still on its
    way: a transform newer than the cloud, a pose sent beside it); the listener fills the buffer in another thread."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return lookup()
        except LookupError as error:
            if time.monotonic() >= deadline or not retry(error):
                raise
        time.sleep(0.005)


class TfListener:
    """The package's own TF listener: /tf and /tf_static (tf2_msgs/TFMessage) into a :class:`TransformBuffer`.

    /tf_static is subscribed transient-local (latched, as TF publishers send it), /tf volatile, both in their own
    callback group so they are taken while a cloud waits for its transform. A lookup at a stamp newer than the newest
    transform waits up to ``wait_s`` for it (a cloud often arrives before the transforms after its stamp), as tf2's
    lookup timeout does. A malformed transform is skipped and counted (``rejected``), never fatal.
    """

    def __init__(self, node: Any, buffer: TransformBuffer, wait_s: float = 0.5) -> None:
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from tf2_msgs.msg import TFMessage

        self.buffer = buffer
        self.wait_s = wait_s
        self.rejected = 0
        group = MutuallyExclusiveCallbackGroup()
        dynamic = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        static = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._subscriptions = [
            node.create_subscription(TFMessage, "/tf", lambda m: self._take(m, False), dynamic, callback_group=group),
            node.create_subscription(TFMessage, "/tf_static", lambda m: self._take(m, True), static,
                                     callback_group=group)]

    def _take(self, message: Any, static: bool) -> None:
        for item in message.transforms:
            t, r = item.transform.translation, item.transform.rotation
            try:
                self.buffer.add(item.header.frame_id, item.child_frame_id, stamp_ns(item.header.stamp),
                                np.array([t.x, t.y, t.z]), np.array([r.x, r.y, r.z, r.w]), static)
            except ValueError:
                self.rejected += 1

    def lookup(self, target: str, source: str, stamp: Any) -> np.ndarray:
        return _waiting(lambda: self.buffer.lookup(target, source, stamp_ns(stamp)), self.wait_s,
                        lambda error: "after the newest" in str(error))


class Tf2RosLookup:
    """TF through tf2_ros (a full ROS install): its Buffer and TransformListener, the same lookup interface."""

    def __init__(self, node: Any, wait_s: float = 0.5) -> None:
        import tf2_ros

        self._tf2_ros = tf2_ros
        self.wait_s = wait_s
        self.buffer = tf2_ros.Buffer()
        self._listener = tf2_ros.TransformListener(self.buffer, node, spin_thread=True)

    def lookup(self, target: str, source: str, stamp: Any) -> np.ndarray:
        from rclpy.duration import Duration
        from rclpy.time import Time

        try:
            message = self.buffer.lookup_transform(target, source, Time.from_msg(stamp),
                                                   timeout=Duration(seconds=self.wait_s))
        except self._tf2_ros.TransformException as error:
            raise LookupError(str(error)) from None
        return transform_msg_matrix(message.transform)


def tf_lookup(node: Any, use_tf2_ros: bool | None = None, max_extrapolation_s: float = 0.0,
              wait_s: float = 0.5) -> tuple[Any, str]:
    """The TF source for ``node``: tf2_ros when importable (unless ``use_tf2_ros`` is False), else the package's own
    listener; returns (lookup object, its name "tf2_ros" or "tf"). wait_s: how long a lookup waits for transforms
    still on their way."""
    if use_tf2_ros is not False:
        try:
            return Tf2RosLookup(node, wait_s), "tf2_ros"
        except ImportError:
            if use_tf2_ros:
                raise
    return TfListener(node, TransformBuffer(max_extrapolation_s), wait_s), "tf"


class PoseTopic:
    """Poses on ``scan/pose`` (geometry_msgs/TransformStamped), kept by (child frame, stamp) for the clouds to come;
    the newest ``keep`` are held. Once a pose has come on the topic, a cloud without its pose waits up to ``wait_s``
    for it (sent beside the cloud, it may arrive after it)."""

    def __init__(self, node: Any, topic: str = "scan/pose", keep: int = 100, qos: Any = None,
                 wait_s: float = 0.5) -> None:
        from geometry_msgs.msg import TransformStamped
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.keep = keep
        self.wait_s = wait_s
        self._poses: dict[tuple[str, int], tuple[str, np.ndarray]] = {}
        self._subscription = node.create_subscription(
            TransformStamped, topic, self.take, qos or QoSProfile(depth=keep, reliability=ReliabilityPolicy.RELIABLE),
            callback_group=MutuallyExclusiveCallbackGroup())

    def take(self, message: Any) -> None:
        key = (message.child_frame_id.lstrip("/"), stamp_ns(message.header.stamp))
        self._poses[key] = (message.header.frame_id.lstrip("/"), transform_msg_matrix(message.transform))
        while len(self._poses) > self.keep:
            self._poses.pop(next(iter(self._poses)))

    def lookup(self, target: str, source: str, stamp: Any) -> np.ndarray:
        return _waiting(lambda: self._lookup(target, source, stamp), self.wait_s if self._poses else 0.0,
                        lambda error: "no pose of" in str(error))

    def _lookup(self, target: str, source: str, stamp: Any) -> np.ndarray:
        found = self._poses.get((source.lstrip("/"), stamp_ns(stamp)))
        if found is None:
            raise LookupError(f"no pose of {source!r} at {stamp_ns(stamp) / 1e9:.3f} s on scan/pose")
        parent, matrix = found
        if parent != target.lstrip("/"):
            raise LookupError(f"the pose of {source!r} on scan/pose is in frame {parent!r}, not the part frame "
                              f"{target!r}")
        return matrix


@dataclass(frozen=True)
class ResolvedPose:
    """The pose of one cloud: (4, 4) part <- cloud frame in mm (None: no source had one), the source's name, and why
    each source before it had none (in order)."""

    pose_mm: np.ndarray | None
    source: str
    skipped: tuple[str, ...] = ()

    @property
    def report(self) -> str:
        """One line for /diagnostics and the inspection's view report."""
        why = f" ({'; '.join(self.skipped)})" if self.skipped else ""
        return f"pose from {self.source}{why}"


class PoseSources:
    """Resolve a cloud's pose from the sources in order (module docstring).

    sources: (name, lookup(target, source, stamp) -> (4, 4) metres) in order of preference. ``resolve`` takes the
    part frame and the ``scanner_pose`` parameter (mm; None when left unset) at each cloud, as the node reads them
    then: without a pose from the sources and without the parameter, a cloud is in the part frame ("part frame",
    pose None).
    """

    def __init__(self, sources: list[tuple[str, Callable[[str, str, Any], np.ndarray]]]) -> None:
        self.sources = sources

    def resolve(self, part_frame: str, cloud_frame: str, stamp: Any,
                parameter_pose_mm: np.ndarray | None = None) -> ResolvedPose:
        skipped = []
        if not cloud_frame:
            skipped.append("the cloud names no frame")
        else:
            for name, lookup in self.sources:
                try:
                    pose = np.array(lookup(part_frame, cloud_frame, stamp), dtype=np.float64)
                except LookupError as error:
                    skipped.append(f"{name}: {error}")
                    continue
                pose[:3, 3] *= 1000.0  # m -> mm
                return ResolvedPose(pose, name, tuple(skipped))
        if parameter_pose_mm is not None:
            return ResolvedPose(parameter_pose_mm, "parameter", tuple(skipped))
        return ResolvedPose(None, "part frame", tuple(skipped))
