"""Replay a bag's scans into the live nodes and record what they publish.

Scans are published in bag order as the raw CDR bytes they were recorded with, one at a time: the next scan goes out
only when the previous one is answered (its boundary state and effect fields arrived, or a node reported an error with
its stamp on /diagnostics), so the nodes are never fed faster than they can take. Every message the nodes publish is
recorded, as it arrives, into an MCAP bag.

A multi-view part (``part``: its id and expected views, from the bag's sidecar) is replayed as one inspection: an
InspectPart goal first, then the bag's records in order (the robot's poses on /tf_static, /tf and scan/pose, each
cloud 0.3 s after the poses before it, as a robot sends them), and the action's result is the part's answer: its
clouds are the views of one part, not parts of their own.
"""

from __future__ import annotations

import logging
import pathlib
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import TransformStamped
from hood_decomp_msgs.msg import BoundaryCorrection, BoundaryState, DisplacementField, EffectFields
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2

from hood_decomp.errors import BagError
from hood_decomp.io.bags import BagWriter, Record, read_bag
from hood_decomp.ros.participant import Participant

logger = logging.getLogger(__name__)

SCAN_TOPIC = "scan/points"
OUTPUTS: dict[str, type] = {
    "hood_decomp/displacement": DisplacementField,
    "hood_decomp/displacement_cloud": PointCloud2,
    "hood_decomp/boundary_state": BoundaryState,
    "hood_decomp/boundary_correction": BoundaryCorrection,
    "hood_decomp/effects": EffectFields,
    "hood_decomp/effects_cloud": PointCloud2,
    "/diagnostics": DiagnosticArray,
}
ANSWERS = ("hood_decomp/boundary_state", "hood_decomp/effects")  # a good scan is answered by both
# topics between the nodes: a message sent on one before its publisher matched every subscription is lost to it
INTERNAL = ("hood_decomp/displacement", "hood_decomp/boundary_state")
MATCH_TIMEOUT_S = 30.0
#: what a multi-view part's replay publishes besides the clouds: the robot's poses
POSE_TOPICS = ("/tf_static", "/tf", "scan/pose")
#: how long a view's cloud follows the poses before it (the scan node looks its pose up when the cloud comes)
POSE_LEAD_S = 0.3


def _msgtype(cls: type) -> str:
    module = cls.__module__.split(".")[0]
    return f"{module}/msg/{cls.__name__}"


def _stamp_key(stamp: object) -> str:
    return f"{stamp.sec}.{stamp.nanosec:09d}"


def _all_matched(peer: Participant, heartbeats: dict[str, dict[str, str]]) -> bool:
    """Whether each publisher of the nodes' internal topics has matched every subscription of that topic that this
    participant has discovered, and the scan subscription has matched our scan publisher, by the nodes' own word:
    each heartbeat carries ``subscribers <topic>`` per output and ``publishers <topic>`` per input (matched counts
    only grow while the nodes run). DDS matches each pair on both sides: our publisher counting the scan node's
    subscription does not mean that the best-effort subscription knows our publisher, and until then it drops what
    comes (a 21 MB first scan was lost that way)."""
    for topic in INTERNAL:
        key = f"subscribers /{topic}"
        reports = [int(values[key]) for values in heartbeats.values() if key in values]
        wanted = peer.node.count_subscribers(topic)
        if len(reports) < peer.node.count_publishers(topic) or any(count < wanted for count in reports):
            return False
    key = f"publishers /{SCAN_TOPIC}"
    reports = [int(values[key]) for values in heartbeats.values() if key in values]
    return bool(reports) and all(count >= peer.node.count_publishers(SCAN_TOPIC) for count in reports)


@dataclass
class ReplayResult:
    """scans: scans published; answered: scans with every expected answer; refused: scans a node reported an error
    for (stamp -> messages); unanswered: stamps that got neither within the timeout; recorded: messages recorded."""

    scans: int = 0
    answered: int = 0
    refused: dict[str, list[str]] = field(default_factory=dict)
    unanswered: list[str] = field(default_factory=list)
    recorded: int = 0
    seconds: float = 0.0
    #: a multi-view part's inspection: part_id, success, message, views_used, views_refused, zones_ok, view_reports
    inspection: dict[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class ReplayPart:
    """A bag that holds one part in several views (sidecar ``part_id`` and ``expected_views``)."""

    part_id: str
    expected_views: int


def replay_bag(bag: str | pathlib.Path, *, record: str | pathlib.Path | None = None, timeout_s: float = 60.0,
               startup_timeout_s: float = 60.0, settle_s: float = 3.0, publish_clock: bool = False,
               answers: Sequence[str] = ANSWERS, part: ReplayPart | None = None) -> ReplayResult:
    """Publish the scans of ``bag`` into running nodes; record their output into ``record`` (a new bag directory).

    timeout_s: longest wait for the answer to one scan (a part: for the action's result after its last view);
    startup_timeout_s: longest wait for the nodes to appear; settle_s: after the last scan, keep recording until
    nothing arrived for this long (late diagnostics, unpaired effect fields). publish_clock: publish each scan's bag
    time on /clock first (for nodes with use_sim_time). part: replay the bag as one multi-view inspection (module
    docstring); its views count as answered when the action fused and estimated them, as refused when a view or
    the part was refused, as unanswered when no result came.
    """
    scans = [r for r in read_bag(bag, topics=[SCAN_TOPIC, *(POSE_TOPICS if part is not None else ())])]
    if part is not None and not any(r.topic == SCAN_TOPIC for r in scans):
        scans = []
    if not scans:
        raise BagError(f"bag {bag} holds no messages on {SCAN_TOPIC}")
    result = ReplayResult()
    answered: dict[str, set[str]] = {}
    heartbeats: dict[str, dict[str, str]] = {}
    last_arrival = [time.monotonic()]
    start = time.monotonic()
    with ExitStack() as stack:
        peer = stack.enter_context(Participant("hood_decomp_replay", depth=10))
        writer = stack.enter_context(BagWriter(record)) if record is not None else None

        def on_output(topic: str, cls: type) -> Callable[[bytes], None]:
            def callback(raw: bytes) -> None:
                if topic != "/diagnostics":  # a heartbeat comes every second: it must not keep the settling open
                    last_arrival[0] = time.monotonic()
                if writer is not None:
                    writer.write(Record(topic, _msgtype(cls), peer.node.get_clock().now().nanoseconds, bytes(raw)))
                    result.recorded += 1
                if topic in answers:
                    key = _stamp_key(deserialize_message(raw, cls).header.stamp)
                    answered.setdefault(key, set()).add(topic)
                elif topic == "/diagnostics":
                    for status in deserialize_message(raw, cls).status:
                        values = {kv.key: kv.value for kv in status.values}
                        if "heartbeat" in values:
                            heartbeats[status.name] = values
                        else:
                            last_arrival[0] = time.monotonic()
                        stamp = values.get("stamp")
                        if status.level == DiagnosticStatus.ERROR and stamp is not None:
                            result.refused.setdefault(stamp, []).append(f"{status.name}: {status.message}")
            return callback

        for topic, cls in OUTPUTS.items():
            peer.subscribe(topic, cls, on_output(topic, cls), raw=True)
        scan_pub = peer.publisher(SCAN_TOPIC, PointCloud2)
        clock_pub = peer.publisher("/clock", Clock) if publish_clock else None
        if not peer.connected([SCAN_TOPIC], list(answers), startup_timeout_s):
            raise BagError(f"no nodes answered within {startup_timeout_s:.0f} s: is something subscribed to "
                           f"{SCAN_TOPIC} and publishing {', '.join(answers)}? (hood-decomp launch --bases B)")
        # The nodes must also have found each other: the field goes to the estimator and the decomposition node
        # (and to our recorder); a field sent before they matched would be lost between them. Our graph shows their
        # endpoints before their own writers and readers have matched each other (DDS matches pair by pair; on a
        # loaded machine the scan node's first field was lost to the estimator that way), so wait for the nodes' own
        # word: their heartbeats count the matched subscriptions of each publisher.
        peer.wait(lambda: peer.node.count_subscribers("hood_decomp/displacement") >= 3, 10.0)
        if not peer.wait(lambda: _all_matched(peer, heartbeats), MATCH_TIMEOUT_S):
            logger.warning("the nodes did not report every subscription of %s matched within %.0f s (nodes without "
                           "a heartbeat?); replaying anyway", ", ".join(INTERNAL), MATCH_TIMEOUT_S)
        if part is not None:
            _replay_part(peer, part, scans, result, timeout_s)
            scans = []
        for index, scan in enumerate(scans, start=1):
            key = _stamp_key(deserialize_message(scan.data, PointCloud2).header.stamp)
            if clock_pub is not None:
                clock_msg = Clock()
                clock_msg.clock.sec, clock_msg.clock.nanosec = divmod(scan.timestamp_ns, 1_000_000_000)
                clock_pub.publish(clock_msg)
            scan_pub.publish(scan.data)
            result.scans += 1
            done = peer.wait(lambda k=key: answered.get(k, set()) >= set(answers) or k in result.refused, timeout_s)
            if not done:
                result.unanswered.append(key)
            elif key not in result.refused:
                result.answered += 1
            state = "refused" if key in result.refused else "answered" if done else "NO ANSWER"
            logger.info("scan %d/%d (stamp %s): %s", index, len(scans), key, state)
        last_arrival[0] = time.monotonic()
        peer.wait(lambda: time.monotonic() - last_arrival[0] > settle_s, settle_s + timeout_s)
    result.seconds = time.monotonic() - start
    return result


def _replay_part(peer: Participant, part: ReplayPart, records: Sequence[Record], result: ReplayResult,
                 timeout_s: float) -> None:
    """One InspectPart of the bag's clouds with the robot's poses of the bag (module docstring); fills ``result``."""
    from hood_decomp_msgs.action import InspectPart
    from rclpy.action import ActionClient
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from tf2_msgs.msg import TFMessage

    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publishers = {"/tf_static": peer.node.create_publisher(TFMessage, "/tf_static", latched),
                  "/tf": peer.publisher("/tf", TFMessage), "scan/pose": peer.publisher("scan/pose", TransformStamped),
                  SCAN_TOPIC: peer.publishers[SCAN_TOPIC]}
    client = ActionClient(peer.node, InspectPart, "hood_decomp/inspect_part")
    try:
        if not (peer.connected(["/tf", "scan/pose"], [], MATCH_TIMEOUT_S) and peer.wait(client.server_is_ready,
                                                                                        MATCH_TIMEOUT_S)):
            raise BagError("no InspectPart server (hood_decomp/inspect_part) or pose subscriptions within "
                           f"{MATCH_TIMEOUT_S:.0f} s: is the scan node running and active?")
        sent = client.send_goal_async(InspectPart.Goal(part_id=part.part_id, expected_views=part.expected_views))
        if not peer.wait(sent.done, MATCH_TIMEOUT_S) or not sent.result().accepted:
            raise BagError(f"the scan node did not accept an inspection of part {part.part_id} (one open already?)")
        keys = []
        for record in records:
            if record.topic == SCAN_TOPIC:
                peer.wait(lambda: False, POSE_LEAD_S)
                keys.append(_stamp_key(deserialize_message(record.data, PointCloud2).header.stamp))
                result.scans += 1
                logger.info("part %s: view %d (stamp %s) sent", part.part_id, len(keys), keys[-1])
            publishers[record.topic].publish(record.data)
        future = sent.result().get_result_async()
        if not peer.wait(future.done, timeout_s + MATCH_TIMEOUT_S):
            result.unanswered += keys
            logger.info("part %s: NO RESULT within %.0f s", part.part_id, timeout_s + MATCH_TIMEOUT_S)
            return
    finally:
        client.destroy()
    answer = future.result().result
    result.inspection = {"part_id": answer.part_id, "success": answer.success, "message": answer.message,
                         "views_used": answer.views_used, "views_refused": answer.views_refused,
                         "zones_ok": answer.zones_ok, "view_reports": list(answer.view_reports)}
    refused = [line for line in answer.view_reports if line.startswith("refused")]
    if answer.success and not refused:
        result.answered += len(keys)
    else:
        for key in keys:
            result.refused.setdefault(key, []).append(f"part {part.part_id}: {answer.message}")
    logger.info("part %s: %s", part.part_id, answer.message)
