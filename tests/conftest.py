"""Test-session setup shared by all tests.

ROS 2 discovery stays on loopback and each test run gets its own domain, so parallel runs never see each other and no
discovery traffic leaves the machine. This must happen before any rclpy.init().
"""

import os

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
os.environ.setdefault("MPLBACKEND", "Agg")
