"""A ROS 2 participant for driving the nodes from outside: replay, tests, benchmarks.

It has its own rclpy context (so it never shares global state with anything else in the process), one node and a
single-threaded executor that runs only while :meth:`Participant.wait` waits.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile

from hood_decomp.ros.node_common import topic_qos, use_fastdds_profile


def latest_heartbeat(diagnostics: Sequence[Any], node_name: str) -> dict[str, str]:
    """The key-values of the newest heartbeat of the hood_decomp node ``node_name`` (e.g. "hood_decomp_scan") among
    collected diagnostic_msgs/DiagnosticArray messages; {} before the first. Its ``publishers <topic>`` values say how
    many publishers the node's subscription has matched: a best-effort subscription drops what comes before."""
    for array in reversed(diagnostics):
        for status in array.status:
            values = {kv.key: kv.value for kv in status.values}
            if status.name == f"hood_decomp/{node_name}" and "heartbeat" in values:
                return values
    return {}


class Participant:
    def __init__(self, name: str, depth: int = 50) -> None:
        use_fastdds_profile()  # the same transports as the nodes (large best-effort clouds)
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.depth = depth
        self.publishers: dict[str, Any] = {}

    def publisher(self, topic: str, cls: type, qos: QoSProfile | None = None) -> Any:
        """A publisher (reliable, volatile, keep-last(depth) unless ``qos``), kept in ``publishers[topic]``."""
        self.publishers[topic] = self.node.create_publisher(cls, topic, qos or topic_qos(self.depth))
        return self.publishers[topic]

    def subscribe(self, topic: str, cls: type, callback: Callable[[Any], None], raw: bool = False,
                  qos: QoSProfile | None = None) -> Any:
        return self.node.create_subscription(cls, topic, callback, qos or topic_qos(self.depth), raw=raw)

    def collect(self, topic: str, cls: type, qos: QoSProfile | None = None) -> list[Any]:
        """Subscribe and return the list the messages are appended to, in arrival order."""
        received: list[Any] = []
        self.subscribe(topic, cls, received.append, qos=qos)
        return received

    def call(self, service: str, cls: type, request: Any, seconds: float,
             give_up: Callable[[], bool] = lambda: False, resend_s: float | None = None) -> Any:
        """Call a service once its server is there; the response, or None when none came within ``seconds`` (or
        ``give_up()`` became true first, e.g. the server's process ended). ``resend_s``: for a request that may be
        repeated (a query), send it again after so many seconds without an answer: a new client's request can reach
        the server before the server's response writer has matched the client's reader, and Fast DDS then drops the
        response ("failed to send response (timeout): client will not receive response"; seen once in 1,285 tests)."""
        deadline = time.monotonic() + seconds
        client = self.node.create_client(cls, service)
        try:
            if not self.wait(lambda: client.service_is_ready() or give_up(), seconds) or give_up():
                return None
            futures = [client.call_async(request)]
            while not self.wait(lambda: any(f.done() for f in futures) or give_up(),
                                max(0.0, min(deadline, time.monotonic() + (resend_s or seconds)) - time.monotonic())):
                if resend_s is None or give_up() or time.monotonic() >= deadline:
                    break
                futures.append(client.call_async(request))
            done = [f for f in futures if f.done()]
            return done[0].result() if done else None
        finally:
            self.node.destroy_client(client)

    def wait(self, condition: Callable[[], bool], seconds: float) -> bool:
        """Process callbacks until ``condition()`` holds (True) or ``seconds`` pass (False)."""
        deadline = time.monotonic() + seconds
        while not condition():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.05)
        return True

    def connected(self, publishing: list[str], subscribed: list[str], seconds: float, subscribers: int = 1) -> bool:
        """Wait until our publishers on ``publishing`` have matched ``subscribers`` subscriptions each and the
        ``subscribed`` topics have a publisher (messages sent before a subscription matched are not delivered)."""
        return self.wait(lambda: all(self.publishers[t].get_subscription_count() >= subscribers for t in publishing)
                         and all(self.node.count_publishers(t) > 0 for t in subscribed), seconds)

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    def __enter__(self) -> Participant:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
