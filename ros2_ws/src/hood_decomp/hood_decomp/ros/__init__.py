"""ROS 2 adapters (message <-> core dataclasses, mm <-> m) and the three thin nodes."""
