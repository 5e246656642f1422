"""The real estimator node with an injected slow stage: every estimate takes SLOW_STAGE_S longer.

Started as a process by tests/ros/test_node_queue.py (``python -m tests.ros.slow_estimator --ros-args ...``) so the
node falls behind a burst on any machine, however fast: the queue test must not depend on machine speed.
"""

from __future__ import annotations

import sys
import time

from hood_decomp.core.method import bases
from hood_decomp.ros import estimator_node

SLOW_STAGE_S = 0.2
_estimate_field = bases.estimate_field


def _slow_estimate_field(*args, **kwargs):
    time.sleep(SLOW_STAGE_S)
    return _estimate_field(*args, **kwargs)


if __name__ == "__main__":
    bases.estimate_field = _slow_estimate_field  # the node imports it from the module when a field arrives
    sys.exit(estimator_node.main(sys.argv))
