"""`hood-decomp launch` as a user runs it: the nodes come up active with --bases and the shipped parameter file, and the
command says so per node."""

from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")

pytestmark = pytest.mark.ros

ROOT = pathlib.Path(__file__).resolve().parents[2]
SHIPPED_PARAMS = ROOT / "ros2_ws/src/hood_decomp/config/hood_decomp.yaml"


def test_launch_with_a_params_file_brings_the_node_to_active(coarse_hood, tmp_path):
    """Fails if the parameter file's `bases: ""` overrides --bases (the issue: the file was applied after -p, the
    nodes ran without bases), or if launch does not report each node's state; Ctrl-C then stops the nodes, status 0."""
    command = [sys.executable, "-m", "hood_decomp.cli", "launch", "--bases", str(coarse_hood.bases_path),
               "--params", str(SHIPPED_PARAMS), "--nodes", "estimator_node"]
    log = tmp_path / "launch.log"
    with open(log, "wb") as output:
        # Ctrl-C as at a terminal: a suite started in the background by a non-interactive shell inherits SIGINT
        # ignored, and Python then keeps it ignored; its own session, so that nothing it started can outlive the test
        process = subprocess.Popen(command, stderr=output, stdout=subprocess.DEVNULL, env=dict(os.environ), cwd=ROOT,
                                   start_new_session=True,
                                   preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120.0
        while "Ctrl-C stops the nodes" not in log.read_text() and process.poll() is None:
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        text = log.read_text()
        assert "hood-decomp launch: estimator_node active" in text, text
    finally:
        process.send_signal(signal.SIGINT)
        try:
            code = process.wait(30)
        except subprocess.TimeoutExpired:
            # a launch (and its nodes) left running would answer the next tests' nodes in the same ROS domain
            os.killpg(process.pid, signal.SIGKILL)
            raise
    assert code == 0, log.read_text()
