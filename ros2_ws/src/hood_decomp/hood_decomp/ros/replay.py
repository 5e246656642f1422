"""Replay a bag's scans into the live nodes and record what they publish.

Scans are published in bag order as the raw CDR bytes they were recorded with, one at a time: the next scan goes out
only when the previous one is answered (its boundary state and effect fields arrived, or a node reported an error with
its stamp on /diagnostics), so the nodes are never fed faster than they can take. Every message the nodes publish is
recorded, as it arrives, into an MCAP bag.
"""

from __future__ import annotations

import logging
import pathlib
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
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


def replay_bag(bag: str | pathlib.Path, *, record: str | pathlib.Path | None = None, timeout_s: float = 60.0,
               startup_timeout_s: float = 60.0, settle_s: float = 3.0, publish_clock: bool = False,
               answers: Sequence[str] = ANSWERS) -> ReplayResult:
    """Publish the scans of ``bag`` into running nodes; record their output into ``record`` (a new bag directory).

    timeout_s: longest wait for the answer to one scan; startup_timeout_s: longest wait for the nodes to appear;
    settle_s: after the last scan, keep recording until nothing arrived for this long (late diagnostics, unpaired
    effect fields). publish_clock: publish each scan's bag time on /clock first (for nodes with use_sim_time).
    """
    scans = [r for r in read_bag(bag, topics=[SCAN_TOPIC])]
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
