"""A node whose keep-last queue overflows (real processes, real middleware): every message it never took is counted
and announced on /diagnostics. Its own module, so no other node hears the burst or shares /diagnostics with it.
The estimator runs with an injected slow stage (tests/ros/slow_estimator.py), so it falls behind on any machine."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import numpy as np
import pytest

from tests.required import require_import

require_import("hood_decomp_msgs.msg", "colcon build", "run inside scripts/with-env after scripts/setup.sh")
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from hood_decomp_msgs.msg import BoundaryState, DisplacementField

from hood_decomp.core.fe.ensemble import solve_members
from hood_decomp.ros.launcher import bring_up, stop_nodes
from hood_decomp.ros.participant import Participant
from tests.ros.test_nodes import _field_msg

pytestmark = pytest.mark.ros


def test_overflowing_queue_is_counted_not_silent(coarse_hood, tmp_path):
    """A burst far faster than the estimator (queue_depth 1, 0.2 s per field): the keep-last queue must drop fields,
    and every dropped one is announced on /diagnostics, so fields in == processed + failed + dropped, and the newest
    is served. Fails if drops go uncounted or unannounced, or if the newest field is not served."""
    root = pathlib.Path(__file__).resolve().parents[2]
    with open(tmp_path / "estimator_node.log", "wb") as log:
        processes = [subprocess.Popen([sys.executable, "-m", "tests.ros.slow_estimator", "--ros-args",
                                       "-p", f"bases:={coarse_hood.bases_path}", "-p", "queue_depth:=1"],
                                      cwd=root, stdout=log, stderr=subprocess.STDOUT)]
    peer = Participant("test_overflow", depth=1000)
    try:
        assert not bring_up(["estimator_node"], 60.0, processes)
        diagnostics = peer.collect("/diagnostics", DiagnosticArray)
        states = peer.collect("hood_decomp/boundary_state", BoundaryState)
        peer.publisher("hood_decomp/displacement", DisplacementField)
        assert peer.connected(["hood_decomp/displacement"], ["hood_decomp/boundary_state"], 60.0)
        good = solve_members(coarse_hood.reduced, np.array([[0.4, -0.3, 0.5, -0.2, 0.3, 0.6]])).normal_displacement[0]
        sent = 200
        for sec in range(1, sent + 1):
            peer.publishers["hood_decomp/displacement"].publish(_field_msg(coarse_hood, good, sec))

        def accounted() -> dict[str, int]:
            """The node's own running totals, from its latest diagnostic (each carries processed/failed/dropped)."""
            if not diagnostics:
                return {}
            values = {kv.key: kv.value for kv in diagnostics[-1].status[0].values}
            return {key: int(values[key]) for key in ("processed", "failed", "dropped")}

        assert peer.wait(lambda: sum(accounted().values()) >= sent and states and states[-1].header.stamp.sec == sent,
                         120.0), (accounted(), len(states))
        peer.wait(lambda: False, 1.0)  # nothing more may arrive
        totals = accounted()
        assert totals["failed"] == 0 and totals["dropped"] > 0 and sum(totals.values()) == sent, totals
        warned = sum(int(kv.value) for array in diagnostics for s in array.status if s.level == DiagnosticStatus.WARN
                     for kv in s.values if kv.key == "dropped_now")
        assert warned == totals["dropped"]  # every drop was announced when it was found
        stamps = [s.header.stamp.sec for s in states]
        assert stamps == sorted(stamps) and len(stamps) == totals["processed"]  # in order, each processed one out
        assert processes[0].poll() is None
    finally:
        peer.close()
        stop_nodes(processes)
