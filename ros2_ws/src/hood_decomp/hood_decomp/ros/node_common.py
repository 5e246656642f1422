"""What the three hood_decomp nodes share: parameter declaration, QoS, diagnostics, a guarded callback.

Nodes stay wiring only: declare parameters, convert, call the core, convert, publish, report. Any failure of one
message (bad input, a core error, a bug) is reported on /diagnostics with the stamp of the offending message and the
node keeps serving the next one. Messages that never reach the node (the keep-last queue overflowed while it was busy,
or they were published before it subscribed) are counted from gaps in the publishers' sequence numbers and reported
too: nothing disappears unannounced. What the package's modules log (``logging``, e.g. the scan field's progress lines)
goes to the node's ROS logger.
"""

from __future__ import annotations

import logging
import traceback
from collections.abc import Callable
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions

from hood_decomp.errors import HoodDecompError

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


def declare(node: Node, name: str, default: Any, description: str,
            low: float | None = None, high: float | None = None) -> Any:
    """Declare a parameter with its description (and range, for numbers) and return its value."""
    descriptor = ParameterDescriptor(description=description)
    if low is not None and high is not None:
        if isinstance(default, int) and not isinstance(default, bool):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high))]
    return node.declare_parameter(name, default, descriptor).value


def topic_qos(depth: int) -> QoSProfile:
    """Reliable, keep-last(depth): large clouds arrive whole (one lost fragment drops a best-effort cloud with stock
    Fast DDS) and a burst of ``depth`` messages waits instead of being dropped. Per-topic overrides follow REP 2003
    through rclpy's ``qos_overrides.<topic>.<publisher|subscription>.<policy>`` parameters."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


OVERRIDABLE = QoSOverridingOptions.with_default_policies()


class Diagnostics:
    """Publishes one DiagnosticStatus per processed message on /diagnostics (name ``hood_decomp/<node>``)."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self._publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.processed = 0
        self.failed = 0
        self.dropped = 0

    def report(self, level: bytes, message: str, stamp: Any = None, **values: object) -> None:
        status = DiagnosticStatus(level=level, name=f"hood_decomp/{self._node.get_name()}", message=message,
                                  hardware_id="hood_decomp")
        if stamp is not None:
            values = {"stamp": f"{stamp.sec}.{stamp.nanosec:09d}", **values}
        values = {**values, "processed": self.processed, "failed": self.failed, "dropped": self.dropped}
        status.values = [KeyValue(key=str(key), value=str(value)) for key, value in values.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self._node.get_clock().now().to_msg()
        self._publisher.publish(array)


def message_stamp(message: Any) -> Any:
    """The message's header stamp, or None for a message without a header."""
    return getattr(getattr(message, "header", None), "stamp", None)


def guarded(node: Node, diagnostics: Diagnostics, what: str,
            handler: Callable[[Any], dict[str, object] | None]) -> Callable[[Any], None]:
    """Wrap a subscription callback: success -> OK diagnostic with the handler's key-values; a HoodDecompError ->
    ERROR diagnostic naming the problem; anything else -> ERROR with the exception type (and the traceback in the
    log). The node never dies from one message."""

    def callback(message: Any) -> None:
        stamp = message_stamp(message)
        try:
            values = handler(message) or {}
        except HoodDecompError as error:
            diagnostics.failed += 1
            node.get_logger().error(f"{what}: {error}")
            diagnostics.report(ERROR, f"{what} refused: {error}", stamp, error=type(error).__name__)
            return
        except Exception as error:  # a bug must not stop the node; it is reported, not hidden
            diagnostics.failed += 1
            node.get_logger().error(f"{what}: unexpected {type(error).__name__}: {error}\n{traceback.format_exc()}")
            diagnostics.report(ERROR, f"{what} failed: {type(error).__name__}: {error}", stamp,
                               error=type(error).__name__)
            return
        diagnostics.processed += 1
        diagnostics.report(OK, f"{what} ok", stamp, **values)

    return callback


def load_bases_or_reason(path: str) -> tuple[Any, str]:
    """(bases, "") or (None, the reason): a node with a bad bases path keeps running and says why on every message."""
    from hood_decomp.io.bases import load_bases

    if not path:
        return None, "no bases file configured (parameter 'bases')"
    try:
        return load_bases(path), ""
    except HoodDecompError as error:
        return None, f"bases not loaded: {error}"


class RosLogHandler(logging.Handler):
    """Forwards :mod:`logging` records to an rclpy logger at the matching severity."""

    def __init__(self, ros_logger: RcutilsLogger) -> None:
        super().__init__()
        self.ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = self.format(record)
            # One call per severity: rclpy ties each call site to the severity it was first called with.
            if record.levelno >= logging.CRITICAL:
                self.ros_logger.fatal(message)
            elif record.levelno >= logging.ERROR:
                self.ros_logger.error(message)
            elif record.levelno >= logging.WARNING:
                self.ros_logger.warning(message)
            elif record.levelno >= logging.INFO:
                self.ros_logger.info(message)
            else:
                self.ros_logger.debug(message)
        except Exception:  # logging must never break the node
            self.handleError(record)


def forward_package_logging(ros_logger: RcutilsLogger) -> None:
    """Send the records of every ``hood_decomp`` logger to ``ros_logger`` (a node's), at that logger's level.

    Once per process: if a forwarding handler is already installed, this does nothing.
    """
    package = logging.getLogger("hood_decomp")
    if any(isinstance(handler, RosLogHandler) for handler in package.handlers):
        return
    package.addHandler(RosLogHandler(ros_logger))
    package.setLevel(int(ros_logger.get_effective_level()))


class HoodNode(Node):
    """What every hood_decomp node has: the ``bases`` and ``queue_depth`` parameters, the bases loaded (or the reason
    they are not, reported at start and on every message), diagnostics, publishers/subscriptions with the project's
    QoS, overridable per topic, and the package's log records in its ROS log."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        forward_package_logging(self.get_logger())
        self.bases_path = declare(self, "bases", "", "path of the bases file (hood-decomp bases --out)")
        self.depth = declare(self, "queue_depth", 10, "messages held per topic while the node is busy", 1, 1000)
        self.diagnostics = Diagnostics(self)
        self.bases, self.bases_error = load_bases_or_reason(self.bases_path)
        if self.bases_error:
            self.diagnostics.report(ERROR, self.bases_error)

    def require_bases(self) -> Any:
        if self.bases is None:
            raise HoodDecompError(self.bases_error)
        return self.bases

    def publisher(self, cls: type, topic: str) -> Any:
        return self.create_publisher(cls, topic, topic_qos(self.depth), qos_overriding_options=OVERRIDABLE)

    def subscription(self, cls: type, topic: str, callback: Callable[[Any], None]) -> Any:
        """Subscribe with the project's QoS. Publishers number their messages from 1, so a gap in a publisher's
        sequence numbers means messages this node never took: the keep-last queue (``queue_depth``) or the
        publisher's own overflowed while the node was busy, or (before the first message seen from a publisher)
        they were published before this node subscribed. A WARN diagnostic says how many, with the stamp of the
        message after the gap."""
        last: dict[bytes, int] = {}

        def counted(message: Any, info: dict[str, Any]) -> None:
            sequence = info.get("publication_sequence_number")
            if sequence:  # 0 / None: the middleware does not number its messages
                publisher = bytes(info["publisher_gid"]["data"])
                previous = last.get(publisher)
                gap = sequence - (previous or 0) - 1
                last[publisher] = max(sequence, previous or 0)
                if gap > 0:
                    self.diagnostics.dropped += gap
                    why = ("published before this node subscribed, or dropped while it was busy" if previous is None
                           else f"dropped while the node was busy: queue_depth {self.depth} overflowed")
                    self.diagnostics.report(WARN, f"{topic}: {gap} message(s) not received ({why})",
                                            message_stamp(message), dropped_now=gap)
            callback(message)

        return self.create_subscription(cls, topic, counted, topic_qos(self.depth),
                                        qos_overriding_options=OVERRIDABLE)

    def guarded(self, what: str, handler: Callable[[Any], dict[str, object] | None]) -> Callable[[Any], None]:
        return guarded(self, self.diagnostics, what, handler)


def spin(node_factory: Callable[[], Node], args: list[str] | None = None) -> int:
    """Console-script body: init, build the node, spin until Ctrl-C or shutdown, clean up."""
    rclpy.init(args=args)
    node = None
    try:
        node = node_factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
