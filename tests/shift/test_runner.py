"""The Dask batch (hood_decomp.shift.runner) on a real dask.distributed LocalCluster of worker processes."""

from __future__ import annotations

import os
import signal
import sqlite3

from hood_decomp.io.history import History
from hood_decomp.shift.part import Options
from hood_decomp.shift.runner import dask_client, run_batch
from hood_decomp.shift.sources import find_sources, iter_tasks
from tests.hood20 import hood20
from tests.shift.conftest import write_fields


def test_worker_killed_mid_batch_every_part_counted_once(tmp_path):
    """Fails if killing a worker process in the middle of the batch loses a part, records one twice, records it as
    failed, or stops the batch."""
    directory = write_fields(tmp_path / "fields", 80)
    sources = find_sources([directory])
    killed: list[int] = []
    with dask_client(None, 2) as client, History(tmp_path / "h.sqlite") as history:
        before = client.run(os.getpid)
        victim = sorted(before.values())[0]

        def kill_once(record):
            if not killed and len(history.done()) >= 20:
                os.kill(victim, signal.SIGKILL)
                killed.append(victim)

        summary = run_batch(client, iter_tasks(sources), 80, str(hood20().bases_path), history, Options(),
                            on_record=kill_once)
        after = client.run(os.getpid)
    assert killed and victim not in after.values(), "the worker was not killed (or not replaced)"
    assert summary.processed == 80 and not summary.failed, summary
    db = sqlite3.connect(tmp_path / "h.sqlite")
    rows = db.execute("SELECT part_id, status FROM parts").fetchall()
    assert len(rows) == 80 and len({r[0] for r in rows}) == 80
    assert {r[1] for r in rows} == {"ok"}
    assert db.execute("SELECT COUNT(*) FROM residuals").fetchone()[0] == 80
