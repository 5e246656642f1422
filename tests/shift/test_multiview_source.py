"""A multi-view bag given to the shift: one part, recorded as failed with the reason, never one part per view."""

from __future__ import annotations

import pathlib

from hood_decomp.shift.part import Options, process_task
from hood_decomp.shift.sources import find_sources, iter_tasks
from tests.hood20 import hood20

BAG = pathlib.Path(__file__).resolve().parents[2] / "bags" / "multiview"


def test_a_multiview_bag_is_one_failed_part_naming_replay():
    """Fails if the shift turns the four views of bags/multiview (sidecar part_id, expected_views 4) into four parts
    (each a partial view registered as a whole part: wrong states in the history), or if the one part it makes is
    not recorded as failed with a reason that names the views and the way to inspect it (replay)."""
    tasks = list(iter_tasks(find_sources([BAG])))
    assert [(t.part_id, t.kind) for t in tasks] == [("hood-multiview-1", "multiview")]
    record = process_task(tasks[0], str(hood20().bases_path), Options())
    assert record.status == "failed" and "several views" in record.error and "hood-decomp replay" in record.error
