"""What the nodes share (hood_decomp.ros.node_common), in-process: the package's log records in the ROS log."""

from __future__ import annotations

import logging

import pytest

from tests.required import require_import

require_import("rclpy", "the ROS 2 environment", "run inside scripts/with-env")
import rclpy.logging

from hood_decomp.ros.node_common import RosLogHandler, forward_package_logging


@pytest.fixture
def package_logger():
    """The ``hood_decomp`` logger, with its handlers and level restored afterwards."""
    package = logging.getLogger("hood_decomp")
    handlers, level = list(package.handlers), package.level
    yield package
    package.handlers[:] = handlers
    package.setLevel(level)


def test_package_log_records_reach_the_ros_log_once(package_logger, capfd):
    ros_logger = rclpy.logging.get_logger("hood_decomp_test_forward")
    forward_package_logging(ros_logger)
    forward_package_logging(ros_logger)  # a second node in the same process adds no second handler
    assert sum(isinstance(h, RosLogHandler) for h in package_logger.handlers) == 1
    module = logging.getLogger("hood_decomp.core.scan.scan_field")
    module.info("first pass: %d points on the skin", 12)
    module.warning("registration fell back")
    module.debug("below the node's level")
    out = "".join(capfd.readouterr())
    assert "[INFO]" in out and "[hood_decomp_test_forward]: first pass: 12 points on the skin" in out
    assert "[WARN]" in out and "registration fell back" in out and "below the node's level" not in out
