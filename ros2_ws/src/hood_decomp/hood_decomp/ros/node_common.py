"""What the three hood_decomp nodes share: a managed life cycle, parameter declaration, QoS, diagnostics with a
heartbeat, a guarded callback.

Nodes stay wiring only: declare parameters, convert, call the core, convert, publish, report. Any failure of one
message (bad input, a core error, a bug) is reported on /diagnostics with the stamp of the offending message and the
node keeps serving the next one. Messages that never reach the node (the keep-last queue overflowed while it was busy,
or they were published before it subscribed) are counted from gaps in the publishers' sequence numbers and reported
too: nothing disappears unannounced. What the package's modules log (``logging``, e.g. the scan field's progress lines)
goes to the node's ROS logger. Each node sends a heartbeat on /diagnostics once a second in every life-cycle state, with
its state, counters and the matched subscriptions of its outputs.
"""

from __future__ import annotations

import json
import logging
import os
import pathlib
import socket
import time
import traceback
from collections import OrderedDict
from collections.abc import Callable, MutableMapping
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, MultiThreadedExecutor
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.lifecycle import LifecycleNode, LifecyclePublisher, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.subscription import Subscription

from hood_decomp.errors import HoodDecompError

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
TRANSIENT_LOCAL, VOLATILE = DurabilityPolicy.TRANSIENT_LOCAL, DurabilityPolicy.VOLATILE
HEARTBEAT_S = 1.0
#: most parts with a reference of their own (3 MB each at paper resolution when all files differ: 3 GB)
MAX_REMEMBERED_REFERENCES = 1000
#: longest part_id, variant and reference path (UTF-8 bytes) a reference is set with: names, not data
MAX_REFERENCE_TEXT_BYTES = 1024
TAKEN_REMEMBERED = 1000  # (publisher, sequence) pairs kept to drop the second copy of a doubly subscribed message


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


def declare_list(node: Node, name: str, kind: Parameter.Type, description: str) -> list[Any]:
    """Declare an array parameter of ``kind`` (e.g. Parameter.Type.DOUBLE_ARRAY) whose default is empty, and return
    its value. rclpy cannot infer the type of an empty list, and a parameter declared with a type but no value has
    none, which makes a bulk parameter get fail; so the empty list is set explicitly when no override gave one."""
    parameter = node.declare_parameter(name, kind, ParameterDescriptor(description=description))
    if parameter.value is None:
        node.set_parameters([Parameter(name, kind, [])])
    return node.get_parameter(name).value


def parse_entries(entries: list[str], what: str) -> dict[str, str]:
    """``["NAME=VALUE", ...]`` (a list parameter) -> {name: value}; an entry without a name or value, or a repeated
    name, is a ValueError naming it and ``what`` the value should be."""
    parsed: dict[str, str] = {}
    for entry in entries:
        name, _, value = (part.strip() for part in entry.partition("="))
        if not name or not value or name in parsed:
            raise ValueError(f"{entry!r}: expected NAME={what}, each name once")
        parsed[name] = value
    return parsed


def topic_qos(depth: int, durability: DurabilityPolicy = VOLATILE) -> QoSProfile:
    """Reliable, keep-last(depth): a burst of ``depth`` messages waits instead of being dropped. Result publishers
    are transient-local (a late subscriber gets the last ``depth``, or as many as its own depth takes); every
    subscription of the nodes is volatile, because a transient-local subscription does not match a volatile publisher.
    Per-topic overrides follow REP 2003 through rclpy's ``qos_overrides.<topic>.<publisher|subscription>.<policy>``
    parameters."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=durability)


def scan_qos(depth: int) -> QoSProfile:
    """The scan node's second subscription of scan/points: best effort, so a best-effort scanner driver (the common
    sensor-data QoS) connects (a reliable subscription does not match it). On one host, with the Fast DDS profile
    shipped in config/fastdds.xml (a 64 MB shared-memory transport), best effort loses no 1M-point cloud; across
    hosts over UDP one lost fragment loses a cloud."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT)


OVERRIDABLE = QoSOverridingOptions.with_default_policies()


FASTDDS_PROFILE_VARIABLE = "FASTDDS_DEFAULT_PROFILES_FILE"


def fastdds_profile() -> pathlib.Path:
    """The Fast DDS profile shipped with the package (config/fastdds.xml: a 64 MB shared-memory transport)."""
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = pathlib.Path(get_package_share_directory("hood_decomp")) / "config" / "fastdds.xml"
        if installed.is_file():
            return installed
    except (ImportError, LookupError, ValueError):
        pass
    return pathlib.Path(__file__).resolve().parents[2] / "config" / "fastdds.xml"


def one_blas_thread(environment: MutableMapping[str, str] = os.environ) -> None:
    """One OpenBLAS thread in a node process unless the user set ``OPENBLAS_NUM_THREADS``: the nodes' linear algebra
    is many small products (the estimator's K x K solves, N x K projections) between which OpenBLAS's idle workers
    spin, on the cores the scan path's own threads and the other two nodes need. Measured under load 10 on 2 cores:
    the estimator's handler took 2.2-3.5 s per field with the default threads, 0.28-0.32 s with one (issue 19). The
    environment variable covers BLAS libraries loaded later (scipy's), threadpoolctl the one numpy has loaded."""
    if "OPENBLAS_NUM_THREADS" in environment:
        return
    environment["OPENBLAS_NUM_THREADS"] = "1"
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")


def blas_threads() -> int:
    """The largest thread count of the BLAS libraries loaded in this process (0 when none is)."""
    from threadpoolctl import threadpool_info

    return max((int(library["num_threads"]) for library in threadpool_info() if library["user_api"] == "blas"),
               default=0)


def small_pages_from_now() -> None:
    """Stop numpy from asking for transparent huge pages for the arrays made from now on (what is prepared so far keeps
    them). A scan's fresh 16-24 MB buffers then take ordinary pages: after a few seconds idle the kernel had to find
    (compact) new huge pages for them, and the first cloud read after idle took 149-215 ms against 56-78 ms with
    ordinary pages, the field step unchanged (default hood, 1M points, issue 19). numpy's switch is private
    (``numpy._core.multiarray._set_madvise_hugepage``): where it is missing nothing changes."""
    import numpy as np

    switch = getattr(np._core.multiarray, "_set_madvise_hugepage", None)
    if switch is not None:
        switch(False)


#: glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
#: whether :func:`keep_freed_memory` took effect in this process (the heartbeat's ``memory_kept``)
_memory_kept = False


def keep_freed_memory() -> bool:
    """Keep the memory a message's arrays free inside the process for the next message: glibc then serves large
    blocks from its heap (no mmap) and never trims the heap's top. Without this, blocks above glibc's 32 MB mmap limit
    and a heap top above its trim threshold go back to the kernel when freed, and the next message faults the same
    pages in again: paper skin, one thread, 2M points 185 ms a scan of which 55 ms in the kernel (33,000 page
    faults), 10M 455 ms of which 118 ms; with the memory kept 125 and 321 ms, no faults (issue 19). The process
    keeps its peak, which is unchanged. Returns whether the C library took the settings (not glibc: nothing changes)."""
    import ctypes

    global _memory_kept
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    _memory_kept = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
    return _memory_kept


def through_middleware(message: Any) -> Any:
    """``message`` serialised and taken back as the middleware hands a received one to a callback. A warm-up sends a
    scan-sized message through this once, so that the first real one does not pay the first large allocation of the
    conversion: a 1M-point cloud took 45-145 ms the first time in a fresh process, 4-20 ms afterwards (issue 19)."""
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(message), type(message))


def use_fastdds_profile(environment: MutableMapping[str, str] = os.environ) -> None:
    """Point Fast DDS at the package's profile unless the user chose one (``FASTDDS_DEFAULT_PROFILES_FILE`` set, even
    empty, is theirs). In this process it must happen before the first rclpy.init; for a child, pass its env."""
    if FASTDDS_PROFILE_VARIABLE not in environment:
        environment[FASTDDS_PROFILE_VARIABLE] = str(fastdds_profile())


class Diagnostics:
    """Publishes DiagnosticStatus on /diagnostics (name ``hood_decomp/<node>``, hardware_id ``<host>:<node's fully
    qualified name>``, one per node): one per processed message, per life-cycle transition and per heartbeat."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self.hardware_id = f"{socket.gethostname()}:{node.get_fully_qualified_name()}"
        self._publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.processed = 0
        self.failed = 0
        self.dropped = 0

    def report(self, level: bytes, message: str, stamp: Any = None, **values: object) -> None:
        status = DiagnosticStatus(level=level, name=f"hood_decomp/{self._node.get_name()}", message=message,
                                  hardware_id=self.hardware_id)
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
    """Wrap a subscription callback: success -> OK diagnostic with the handler's key-values and ``seconds``, the
    handler's wall time (the node's share of a message's latency); WARN with the message ``<what> done with a
    warning: <warning>`` when they hold a non-empty ``warning`` (served, but something the operator must know); a
    HoodDecompError -> ERROR diagnostic naming the problem; anything else -> ERROR with the exception type (and the
    traceback in the log). The node never dies from one message."""

    def callback(message: Any) -> None:
        stamp = message_stamp(message)
        start = time.perf_counter()
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
        values["seconds"] = f"{time.perf_counter() - start:.4f}"
        warning = str(values.pop("warning", "") or "")
        if warning:
            node.get_logger().warning(f"{what}: {warning}")
            diagnostics.report(WARN, f"{what} done with a warning: {warning}", stamp, **values)
        else:
            diagnostics.report(OK, f"{what} ok", stamp, **values)

    return callback


def load_bases_or_reason(path: str) -> tuple[Any, str]:
    """(bases, "") or (None, the reason): a node with a bad bases file fails its configure transition and stays
    alive, unconfigured, saying why. Any failure of the loader (also one it did not foresee, e.g. memory) is a
    reason, never an exception."""
    from hood_decomp.io.bases import load_bases

    if not path:
        return None, "no bases file configured (parameter 'bases')"
    try:
        return load_bases(path), ""
    except HoodDecompError as error:
        return None, f"bases not loaded: {error}"
    except Exception as error:  # the node must survive and name it
        return None, f"bases {path} not loaded: {type(error).__name__}: {error}"


def bases_provenance_values(variant_bases: dict[str, Any]) -> dict[str, str]:
    """Diagnostic key-values of the bases served (variant "" = default): ``bases_id`` and ``calibration`` (the
    calibration's id, "none" for uncalibrated bases) of the default variant, and per variant ``bases_provenance``
    (``bases_provenance <variant>``): what ``estimate --json`` reports of them (io.bases.bases_provenance: bases_id
    and the calibration's id, entries, leave-one-out RMS, physical factors with their std, model discrepancy), JSON."""
    from hood_decomp.io.bases import bases_provenance

    values: dict[str, str] = {}
    for variant, bases in variant_bases.items():
        provenance = bases_provenance(bases)
        if not variant:
            calibration = provenance["calibration"]
            values["bases_id"] = provenance["bases_id"]
            values["calibration"] = "none" if calibration is None else calibration["id"]
        key = f"bases_provenance {variant}" if variant else "bases_provenance"
        values[key] = json.dumps(provenance, sort_keys=True)
    return values


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


class HoodNode(LifecycleNode):
    """What every hood_decomp node has: a managed life cycle, the ``bases`` and ``queue_depth`` parameters,
    diagnostics with a 1 Hz heartbeat, publishers/subscriptions with the project's QoS (overridable per topic), and
    the package's log records in its ROS log.

    Life cycle (REP 2002, rclpy.lifecycle): ``configure`` loads and checks the bases and creates the publishers
    (a failure is a failed transition: the node stays unconfigured, alive, with the reason in its log, on
    /diagnostics and in every heartbeat); ``activate`` creates the subscriptions, so the node serves only when active;
    ``deactivate`` and ``cleanup`` undo them. A subclass implements :meth:`configure_node` (publishers, one-time
    preparation of the bases) and :meth:`activate_node` (subscriptions, timers). Parameters named in
    ``configure_parameters`` are read at configure: a change is refused unless the node is unconfigured (set it,
    then configure). Every other parameter is read when it is used, so ``ros2 param set`` takes effect at the next
    message; :meth:`check_parameter` may refuse a bad value with a reason.
    """

    configure_parameters: frozenset[str] = frozenset({"bases", "queue_depth", "variants"})

    def __init__(self, name: str) -> None:
        super().__init__(name)
        forward_package_logging(self.get_logger())
        declare(self, "bases", "", "path of the bases file (hood-decomp bases --out); read at configure")
        declare(self, "queue_depth", 10, "messages held per topic while the node is busy; read at configure", 1, 1000)
        declare_list(self, "variants", Parameter.Type.STRING_ARRAY, "further part variants this node serves, "
                     "VARIANT=PATH of each variant's bases file; a field is served with the bases of its model_id; "
                     "read at configure")
        declare(self, "autostart", False, "configure and activate at start-up (for a node started alone, without a "
                "lifecycle manager such as hood-decomp launch)")
        self.state = "unconfigured"
        self.configure_error = ""
        self.bases: Any = None  # the default variant's
        self.variant_bases: dict[str, Any] = {}  # variant ("" = default) -> bases
        self.provenance: dict[str, str] = {}  # heartbeat key -> the bases' id and calibration (JSON), per variant
        self.depth = 10
        self._outputs: list[Any] = []
        self._inputs: list[Any] = []
        self.diagnostics = Diagnostics(self)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        # the heartbeat has its own callback group, so a multi-threaded executor sends it while a message is processed
        self.create_timer(HEARTBEAT_S, self.heartbeat, callback_group=MutuallyExclusiveCallbackGroup())

    def param(self, name: str) -> Any:
        """A parameter's current value (read at use, so a change applies to the next message)."""
        return self.get_parameter(name).value

    # --- parameters -----------------------------------------------------------------------------------------------
    def check_parameter(self, parameter: Parameter) -> str:
        """The reason a new value of ``parameter`` is refused, or "" (subclasses check their own and call this)."""
        if parameter.name == "variants" and parameter.value is not None:
            try:
                parse_entries(list(parameter.value), "PATH")
            except ValueError as error:
                return str(error)
        return ""

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name in self.configure_parameters and self.state != "unconfigured":
                return SetParametersResult(successful=False, reason=(
                    f"{parameter.name} is read at configure and the node is {self.state}: deactivate and clean it "
                    "up, set the parameter, configure again"))
            reason = self.check_parameter(parameter)
            if reason:
                return SetParametersResult(successful=False, reason=f"{parameter.name}: {reason}")
        self.accept_parameters(parameters)
        return SetParametersResult(successful=True)

    def accept_parameters(self, parameters: list[Parameter]) -> None:
        """Called once every parameter of a set passed :meth:`check_parameter` (one set is accepted or refused whole):
        a subclass takes what it prepared while checking (e.g. a file it read)."""

    # --- life cycle -----------------------------------------------------------------------------------------------
    def configure_node(self) -> None:
        """Create the publishers (:meth:`publisher`) and prepare what ``self.bases`` allows; raise to fail."""

    def activate_node(self) -> None:
        """Create the subscriptions (:meth:`subscription`) and timers (:meth:`timer`)."""

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        path = self.param("bases")
        self.depth = int(self.param("queue_depth"))
        try:
            self.variant_bases = self._load_variants(path)
            self.bases = self.variant_bases[""]
            self.provenance = bases_provenance_values(self.variant_bases)
            self.configure_node()
            small_pages_from_now()  # the bases and prepared skins keep their huge pages; per-message buffers not
        except Exception as error:  # any failure is a failed transition, never a dead process
            reason = str(error) if isinstance(error, HoodDecompError) else f"{type(error).__name__}: {error}"
            self.get_logger().error(f"configure failed: {reason}")
            self._destroy(self._outputs)
            self.bases, self.variant_bases, self.provenance, self.configure_error = None, {}, {}, reason
            self.diagnostics.report(ERROR, f"configure failed: {reason}", bases=path)
            return TransitionCallbackReturn.FAILURE
        self.configure_error = ""
        self.state = "inactive"
        served = ", ".join(f"{variant or 'default'} (model {bases.model_id})"
                           for variant, bases in self.variant_bases.items())
        self.get_logger().info(f"configured with bases {path}; serving {served}")
        self.diagnostics.report(OK, "configured", bases=path, variants=served, **self.provenance)
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.activate_node()
        self.state = "active"
        self.diagnostics.report(OK, "active")
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy(self._inputs)
        self.state = "inactive"
        self.diagnostics.report(WARN, "inactive: not serving")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy(self._outputs)
        self.bases, self.variant_bases, self.provenance = None, {}, {}
        self.state = "unconfigured"
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._destroy(self._inputs)
        self._destroy(self._outputs)
        self.state = "finalized"
        return super().on_shutdown(state)

    def _destroy(self, entities: list[Any]) -> None:
        for entity in entities:
            if isinstance(entity, LifecyclePublisher):
                self.destroy_lifecycle_publisher(entity)
            elif isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            else:
                self.destroy_timer(entity)
        entities.clear()

    # --- heartbeat ------------------------------------------------------------------------------------------------
    def heartbeat_values(self) -> dict[str, object]:
        """Key-values of the heartbeat: the state, per output topic its matched subscriptions and per input topic its
        matched publishers (DDS matches each pair on both sides; a sender that counts our subscription may not be
        counted by it yet, and a best-effort subscription loses what comes before), the BLAS threads in use,
        whether freed memory is kept for the next message (:func:`keep_freed_memory`) and the process id (two nodes of
        one name on one ROS domain answer each other's lifecycle calls: the launcher tells them apart by it), and the
        bases' id and calibration when configured (:func:`bases_provenance_values`)."""
        return {"state": self.state, "blas_threads": blas_threads(), "memory_kept": _memory_kept, "pid": os.getpid(),
                **self.provenance,
                **{f"subscribers {entity.topic_name}": entity.get_subscription_count()
                   for entity in self._outputs if isinstance(entity, LifecyclePublisher)},
                **{f"publishers {entity.topic_name}": entity.get_publisher_count()
                   for entity in self._inputs if isinstance(entity, Subscription)}}

    def heartbeat(self) -> None:
        """Once a second in every state, so an aggregator never shows the node STALE between parts."""
        if self.state == "active":
            level, message = OK, "active: serving"
        elif self.configure_error:
            level, message = ERROR, f"{self.state}: configure failed: {self.configure_error}"
        else:
            level, message = WARN, f"{self.state}: not serving"
        self.diagnostics.report(level, message, heartbeat=True, **self.heartbeat_values())

    # --- entities -------------------------------------------------------------------------------------------------
    def _load_variants(self, path: str) -> dict[str, Any]:
        """variant ("" = default, from ``bases``) -> loaded bases; a file that does not load, or two variants of
        the same model_id (a field could not be told apart), is a HoodDecompError naming the variant."""
        files = {"": path, **parse_entries(list(self.param("variants")), "PATH")}
        loaded: dict[str, Any] = {}
        for variant, file in files.items():
            bases, reason = load_bases_or_reason(file)
            if bases is None:
                raise HoodDecompError(f"variant {variant}: {reason}" if variant else reason)
            twin = next((name for name, other in loaded.items() if other.model_id == bases.model_id), None)
            if twin is not None:
                raise HoodDecompError(f"variants {twin or 'default'!r} and {variant!r} have the same model_id "
                                      f"{bases.model_id}: their fields could not be told apart")
            loaded[variant] = bases
        return loaded

    def require_bases(self) -> Any:
        if self.bases is None:  # only reachable when a subclass uses it outside the active state
            raise HoodDecompError(f"no bases loaded (node {self.state})")
        return self.bases

    def bases_for_model(self, model_id: str) -> Any:
        """The bases of the variant whose model_id a field carries; a HoodDecompError naming what is served else."""
        self.require_bases()
        for bases in self.variant_bases.values():
            if bases.model_id == model_id:
                return bases
        served = ", ".join(f"{bases.model_id} ({variant or 'default'})"
                           for variant, bases in self.variant_bases.items())
        raise HoodDecompError(f"field of model_id {model_id!r}: this node serves model_id {served}")

    def bases_for_variant(self, variant: str) -> Any:
        """The bases of a part variant by name ("" = the default); a HoodDecompError naming the served ones else."""
        self.require_bases()
        if variant not in self.variant_bases:
            raise HoodDecompError(f"variant {variant!r} is not served here (served: "
                                  f"{', '.join(name or 'default' for name in self.variant_bases)}; parameter variants)")
        return self.variant_bases[variant]

    def publisher(self, cls: type, topic: str, latest: bool = False) -> Any:
        """A publisher, created at configure and active with the node. ``latest``: a result topic, transient-local,
        so a subscriber that comes later (a controller that reconnects) still receives the last results."""
        qos = topic_qos(self.depth, TRANSIENT_LOCAL if latest else VOLATILE)
        publisher = self.create_lifecycle_publisher(cls, topic, qos, qos_overriding_options=OVERRIDABLE)
        self._outputs.append(publisher)
        return publisher

    def timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        timer = self.create_timer(period_s, callback)
        self._inputs.append(timer)
        return timer

    def subscription(self, cls: type, topic: str, callback: Callable[[Any], None],
                     any_reliability: bool = False) -> list[Any]:
        """Subscribe with the project's QoS, for as long as the node is active. Publishers number their messages
        from 1, so a gap in a publisher's sequence numbers means messages this node never took: the keep-last queue
        (``queue_depth``) or the publisher's own overflowed while the node was busy, or (before the first message
        seen from a publisher) they were published before this node subscribed. A WARN diagnostic says how many,
        with the stamp of the message after the gap.

        ``any_reliability``: a second, best-effort subscription of the topic (:func:`scan_qos`, its overrides under
        the id "best_effort": ``qos_overrides.<topic>.subscription_best_effort.<policy>``), so best-effort publishers
        connect too. A reliable publisher matches both and each message is taken once (by publisher and sequence
        number; the second copy is dropped): reliable delivery stays reliable. One best-effort subscription alone
        lost the first two 21 MB clouds of every reliable publisher (Fast DDS 3.2.3, measured)."""
        last: dict[bytes, int] = {}
        taken: OrderedDict[tuple[bytes, int], None] = OrderedDict()

        def counted(message: Any, info: dict[str, Any]) -> None:
            sequence = info.get("publication_sequence_number")
            if sequence:  # 0 / None: the middleware does not number its messages
                publisher = bytes(info["publisher_gid"]["data"])
                if (publisher, sequence) in taken:  # the other subscription's copy
                    return
                taken[(publisher, sequence)] = None
                while len(taken) > TAKEN_REMEMBERED:
                    taken.popitem(last=False)
                previous = last.get(publisher)
                if previous is not None and sequence < previous:  # a late copy of one counted as not received
                    self.diagnostics.dropped -= 1
                gap = sequence - (previous or 0) - 1
                last[publisher] = max(sequence, previous or 0)
                if gap > 0:
                    self.diagnostics.dropped += gap
                    why = ("published before this node subscribed, or dropped while it was busy" if previous is None
                           else f"dropped while the node was busy: queue_depth {self.depth} overflowed")
                    self.diagnostics.report(WARN, f"{topic}: {gap} message(s) not received ({why})",
                                            message_stamp(message), dropped_now=gap)
            callback(message)

        profiles = [(topic_qos(self.depth), OVERRIDABLE)]
        if any_reliability:
            profiles.append((scan_qos(self.depth), QoSOverridingOptions.with_default_policies(entity_id="best_effort")))
        subscriptions = [self.create_subscription(cls, topic, counted, qos, qos_overriding_options=options)
                         for qos, options in profiles]
        self._inputs.extend(subscriptions)
        return subscriptions

    def guarded(self, what: str, handler: Callable[[Any], dict[str, object] | None]) -> Callable[[Any], None]:
        return guarded(self, self.diagnostics, what, handler)


def too_long(text: str, what: str) -> None:
    """HoodDecompError when ``text`` is longer than MAX_REFERENCE_TEXT_BYTES (UTF-8): a name, not data."""
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_REFERENCE_TEXT_BYTES:
        raise HoodDecompError(f"{what} of {size} bytes: at most {MAX_REFERENCE_TEXT_BYTES}")


def check_reference_path(path: str) -> None:
    """HoodDecompError unless ``path`` is absolute and at most MAX_REFERENCE_TEXT_BYTES: a relative one would resolve
    against the node's working directory (wherever its launcher ran), not the caller's, and read another file than
    meant."""
    too_long(path, "reference path")
    if not os.path.isabs(path):
        raise HoodDecompError(f"reference {path!r} is a relative path: give it absolute (the node would resolve it "
                              "against its own working directory, not yours)")


class ReferencedNode(HoodNode):
    """A HoodNode that estimates from fields (the estimator and the decomposition node): each field is made
    reference-relative before it is used (measured - reference + the model's field at the reference's known state, so
    a static model error cancels; docs/calibration.md), with the same code as the CLI's ``--reference``
    (io.calibration_files.read_reference).

    A reference per cell: the parameter ``reference`` (a REF.json exactly as ``--reference`` takes it; empty: none),
    for the fields of the default bases' model_id. It is read at configure (a bad one fails the transition, saying
    why) and when it changes while configured: a file that does not read, a reference of another model_id, bases
    without a reduced model, ... refuse the change with a one-line reason; the node keeps its old reference and keeps
    serving. A reference per part: the service ``<node>/set_reference`` (hood_decomp_msgs/SetReference: part_id,
    variant, path; an empty path forgets the part's), at most ``remembered_references`` parts (the oldest forgotten
    first, and said so; parts naming the same unchanged file share one read). A field whose part_id has one is made
    relative to it, else to the cell's. After a bases swap (cleanup, configure) every reference is read again with the
    new bases; a part reference that no longer reads is forgotten with a WARN naming it. Every result says which
    reference it used (``reference`` in the output message and the diagnostic: "cell:PATH", "part:PATH" or empty);
    the heartbeat names the cell's and counts the parts' and the files read for them."""

    def __init__(self, name: str) -> None:
        from hood_decomp_msgs.srv import SetReference

        self.cell_reference: Any = None  # io.calibration_files.Reference of the parameter, while configured
        self.part_references: OrderedDict[str, tuple[str, Any]] = OrderedDict()  # part_id -> (variant, Reference)
        self._staged: dict[str, Any] = {}  # parameter -> what check_parameter read, taken by accept_parameters
        super().__init__(name)
        declare(self, "reference", "", "reference of the cell: REF.json, an absolute path (a part in a known "
                "state, as --reference takes it) every field of the default bases' model is made relative to, unless "
                "its part has its own (service set_reference); empty: none. Read at configure and when changed")
        declare(self, "remembered_references", 100, "parts whose own reference (service set_reference) is kept, "
                "oldest forgotten first. Each file read holds two float64 per skin node (0.5 MB on the default hood, "
                "3 MB at paper resolution: 1000 parts of distinct files, 3 GB); parts naming the same unchanged "
                "file share one", 1, MAX_REMEMBERED_REFERENCES)
        self.create_service(SetReference, "~/set_reference", self.on_set_reference)

    # --- reading ----------------------------------------------------------------------------------------------------
    def shared_reference(self, path: str, variant: str, held: list[tuple[str, Any]]) -> Any:
        """The reference of REF.json ``path`` for ``variant``: one of ``held`` ((variant, Reference) pairs) that read
        the same files, unchanged since, for the same variant (shared: 16 bytes a skin node each), else read now."""
        from hood_decomp.io.calibration_files import file_key

        check_reference_path(path)  # before the file is looked at: a relative path is never shared either
        try:
            source = file_key(path)
        except OSError:
            source = None  # not shared: read_reference names the problem
        shared = next((reference for held_variant, reference in held
                       if source is not None and held_variant == variant and reference.reads(source)), None)
        return shared if shared is not None else self.read_reference(path, variant)

    def held_references(self) -> list[tuple[str, Any]]:
        """(variant, Reference) of every reference held: the parts' and the cell's (of the default variant)."""
        cell = [("", self.cell_reference)] if self.cell_reference is not None else []
        return list(self.part_references.values()) + cell

    def read_reference(self, path: str, variant: str = "") -> Any:
        """The REF.json ``path`` read for the bases of ``variant`` (io.calibration_files.read_reference); a
        HoodDecompError naming the problem (:func:`check_reference_path` first)."""
        from hood_decomp.io.calibration_files import read_reference

        check_reference_path(path)
        try:
            return read_reference(path, self.bases_for_variant(variant), float(self.param("min_coverage")))
        except HoodDecompError:
            raise
        except Exception as error:  # e.g. memory: a reason, never a dead node
            raise HoodDecompError(f"reference {path} not read: {type(error).__name__}: {error}") from error

    def check_parameter(self, parameter: Parameter) -> str:
        if parameter.name == "reference" and self.variant_bases:  # unconfigured: read at configure
            try:
                self._staged["reference"] = self.read_reference(str(parameter.value)) if parameter.value else None
            except HoodDecompError as error:
                return f"{error} (the node keeps {self.reference_label(self.cell_reference, 'cell') or 'none'})"
        return super().check_parameter(parameter)

    def accept_parameters(self, parameters: list[Parameter]) -> None:
        staged = self._staged.pop("reference", False)  # what a refused set left behind is never taken
        names = {parameter.name: parameter.value for parameter in parameters}
        if staged is not False and "reference" in names:
            self.cell_reference = staged
            self.diagnostics.report(OK, "reference set", reference=self.reference_label(self.cell_reference, "cell"))
        if "remembered_references" in names:  # a lower bound applies now, not at the next part's reference
            limit = int(names["remembered_references"])
            forgotten = self._forget_beyond(limit)
            if forgotten:
                message = f"remembered_references {limit}: part reference(s) forgotten: {', '.join(forgotten)}"
                self.get_logger().warning(message)
                self.diagnostics.report(WARN, message, part_references=len(self.part_references))
        super().accept_parameters(parameters)

    def configure_node(self) -> None:
        """Read the cell's reference (a bad one fails the transition) and every part's again with the new bases, into
        temporaries: :meth:`on_configure` takes them when the whole transition succeeds."""
        path = str(self.param("reference"))
        cell = self.read_reference(path) if path else None
        forgotten, parts = [], OrderedDict()
        for part_id, (variant, reference) in self.part_references.items():
            try:  # shared with those read already with the new bases, as they were shared before
                held = list(parts.values()) + ([("", cell)] if cell is not None else [])
                parts[part_id] = (variant, self.shared_reference(reference.path, variant, held))
            except HoodDecompError as error:
                forgotten.append(f"{part_id}: {error}")
        self._staged["configure"] = (cell, parts, forgotten)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = super().on_configure(state)
        cell, parts, forgotten = self._staged.pop("configure", (None, self.part_references, []))
        if result != TransitionCallbackReturn.SUCCESS:
            # no reference of bases that are gone; the parts keep theirs as they were (read again at configure)
            self.cell_reference = None
            return result
        self.cell_reference, self.part_references = cell, parts
        if forgotten:
            self.get_logger().warning(f"part references forgotten: {'; '.join(forgotten)}")
            self.diagnostics.report(WARN, f"{len(forgotten)} part reference(s) forgotten at configure: "
                                    f"{'; '.join(forgotten)}")
        return result

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.cell_reference = None  # prepared with the bases that go now; part references are read again at configure
        return super().on_cleanup(state)

    # --- the service ------------------------------------------------------------------------------------------------
    def on_set_reference(self, request: Any, response: Any) -> Any:
        """SetReference: read the part's REF.json with its variant's bases (or forget it: empty path); refused with
        a one-line reason (the part keeps what it had) when the node is not configured or the file does not serve."""
        # taken as sent, not stripped: a field's part_id is matched as it comes (messages.part_id_of)
        part_id, path = request.part_id, request.path
        try:
            too_long(part_id, "part_id")
            too_long(request.variant, "variant")
            response.accepted, response.message = self._set_reference(part_id, request.variant, path)
        except HoodDecompError as error:
            response.accepted, response.message = False, str(error)
        level = OK if response.accepted else WARN
        shown = part_id if len(part_id) <= 80 else part_id[:77] + "..."
        self.diagnostics.report(level, f"set_reference {shown!r}: {response.message}", part_id=shown,
                                part_references=len(self.part_references))
        return response

    def _set_reference(self, part_id: str, variant: str, path: str) -> tuple[bool, str]:
        if not part_id:
            return False, "part_id is empty: name the part (the cell's reference is the parameter 'reference')"
        if not path:
            had = self.part_references.pop(part_id, None)
            return True, (f"part {part_id} forgot its reference {had[1].path}" if had else
                          f"part {part_id} had no reference of its own")
        if not self.variant_bases:
            return False, f"node {self.state}: configure it first (references are read with its bases)"
        try:
            reference = self.shared_reference(path, variant, self.held_references())
        except HoodDecompError as error:
            kept = self.part_references.get(part_id)
            return False, f"{error} (part {part_id} keeps {kept[1].path if kept else 'no reference of its own'})"
        self.part_references.pop(part_id, None)
        self.part_references[part_id] = (variant, reference)
        message = f"part {part_id}: reference {reference.name} of {path} (model {reference.model_id})"
        return True, message + "".join(f"; part {oldest}'s reference forgotten (remembered_references)"
                                       for oldest in self._forget_beyond(int(self.param("remembered_references"))))

    def _forget_beyond(self, limit: int) -> list[str]:
        """Forget the oldest part references beyond ``limit``; their part ids."""
        forgotten = []
        while len(self.part_references) > limit:
            forgotten.append(self.part_references.popitem(last=False)[0])
        return forgotten

    # --- use --------------------------------------------------------------------------------------------------------
    @staticmethod
    def reference_label(reference: Any, scope: str) -> str:
        """What an output says of the reference it used: "cell:PATH" / "part:PATH"
        (io.calibration_files.Reference.label), "" for none."""
        return "" if reference is None else reference.label(scope)

    def field_of(self, msg: Any) -> tuple[Any, Any, str]:
        """A DisplacementField message -> (its bases, the field made relative to the part's reference, else the
        cell's when of the same model, else as measured; the reference's label). A part whose own reference is of
        another model than its field is refused by name (never the cell's used in its place)."""
        from hood_decomp.ros import messages

        bases = self.bases_for_model(msg.model_id)
        field = messages.msg_to_field(msg)
        part_id = messages.part_id_of(msg)
        own = self.part_references.get(part_id)
        if own is not None:
            reference, scope = own[1], "part"
            if reference.model_id != msg.model_id:
                raise HoodDecompError(f"part {part_id}'s reference {reference.path} is of model {reference.model_id},"
                                      f" its field of model {msg.model_id}: set its reference again (set_reference)")
        elif self.cell_reference is not None and self.cell_reference.model_id == msg.model_id:
            reference, scope = self.cell_reference, "cell"
        else:
            return bases, field, ""
        return bases, reference.relative(field, bases), self.reference_label(reference, scope)

    def heartbeat_values(self) -> dict[str, object]:
        return {**super().heartbeat_values(), "reference": self.reference_label(self.cell_reference, "cell") or "none",
                "part_references": len(self.part_references),
                "part_reference_files": len({id(reference) for _, reference in self.part_references.values()})}


def spin_executor(executor: Executor) -> None:
    """Spin ``executor`` until its context shuts down, as rclpy.spin does, through rclpy's race between building a
    wait set and destroying an entity: the executor enters an event handler (a publisher's or subscription's QoS
    events) and adds it to its wait set without holding its handle, so a lifecycle transition that destroys the
    publisher in the other executor thread meanwhile raised InvalidHandle here and ended the node's process (seen
    once in 1,307 tests, a cleanup; ros2/rclpy#1284). The next wait set is built without the destroyed entity."""
    while executor.context.ok():
        try:
            executor.spin_once()
        except InvalidHandle:
            continue


def spin(node_factory: Callable[[], HoodNode], args: list[str] | None = None) -> int:
    """Console-script body: init, build the node (unconfigured; configured and activated here when its
    ``autostart`` parameter is true), spin until Ctrl-C or shutdown, clean up. Two executor threads: the heartbeat
    goes out while a message is processed. One BLAS thread unless the user chose otherwise (:func:`one_blas_thread`);
    freed memory kept for the next message (:func:`keep_freed_memory`)."""
    one_blas_thread()
    keep_freed_memory()
    use_fastdds_profile()
    rclpy.init(args=args)
    node = None
    try:
        node = node_factory()
        if node.param("autostart") and node.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            node.trigger_activate()
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        spin_executor(executor)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
