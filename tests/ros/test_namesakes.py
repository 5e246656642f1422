"""Two nodes of one name on one ROS domain (another user's cell, a second run): the launcher must not take the other
process's answers for its own node's."""

from __future__ import annotations

import os

import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
from hood_decomp.errors import HoodDecompError
from hood_decomp.ros.launcher import start_nodes, stop_nodes

pytestmark = pytest.mark.ros


def test_a_namesake_in_another_process_is_named_not_answered_for(coarse_hood, tmp_path):
    """An active estimator already runs on this domain; a second one is started. Fails if bring-up reports the second
    as up (before: the first one's get_state answer "active" was taken for it, within a second, while the second had
    not even started), or if the error does not name the other process and the domain."""
    first = start_nodes(coarse_hood.bases_path, nodes=("estimator_node",), log_dir=tmp_path)
    try:
        (tmp_path / "second").mkdir()
        with pytest.raises(HoodDecompError) as error:
            stop_nodes(start_nodes(coarse_hood.bases_path, nodes=("estimator_node",), log_dir=tmp_path / "second"))
        assert (f"another process (pid {first[0].pid}) on ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']} also runs a node "
                "named /hood_decomp_estimator") in str(error.value)
        assert first[0].poll() is None
    finally:
        stop_nodes(first)
