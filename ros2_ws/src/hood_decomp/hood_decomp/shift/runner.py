"""A batch of parts on Dask: a local cluster of worker processes by default, or a running scheduler by address.

The client submits one task per part (:func:`hood_decomp.shift.part.process_task`), at most ``window`` in flight so
a bag's clouds are read only as fast as they are processed, and writes each result to the history as it arrives
(the one writer of the database). A part whose task fails for good (its worker died more often than the scheduler
allows, or an unexpected error) is recorded as failed with the reason; a worker that dies has its tasks run again
elsewhere by the scheduler, and the history's (source, part_id) uniqueness keeps every part counted once. Progress
(parts done / total, rate, ETA, failures) goes to this module's logger.
"""

from __future__ import annotations

import logging
import resource
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from hood_decomp.io.history import History, PartRecord
from hood_decomp.shift.part import Options, PartTask, process_task

logger = logging.getLogger(__name__)

#: seconds between two progress lines at most (a line is also written every 5 % of the batch)
PROGRESS_PERIOD_S = 10.0


@dataclass(frozen=True)
class BatchSummary:
    """total: parts in the inputs; skipped: already recorded as processed in the history; processed: parts recorded
    by this run; failed: (source, part_id, error) of the failed ones; seconds: wall time; workers: worker count."""

    total: int
    skipped: int
    processed: int
    failed: tuple[tuple[str, str, str], ...]
    seconds: float
    workers: int

    @property
    def rate(self) -> float:
        return self.processed / self.seconds if self.seconds > 0 else float("nan")


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[object]:
    """A dask.distributed Client: on the scheduler at ``scheduler`` ("tcp://host:8786"), else on a LocalCluster of
    ``workers`` processes with one thread each (the core's numpy already uses the cores it is given)."""
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        yield client


def _peak_rss_mb() -> float:
    """Peak resident memory of this process, MB: VmHWM of /proc/self/status on Linux (ru_maxrss survives exec, so a
    spawned worker would report its parent's peak), else ru_maxrss."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def worker_peak_memory_mb(client: object) -> dict[str, float]:
    """Peak resident memory of every worker process so far, MB, by worker address."""
    return dict(client.run(_peak_rss_mb))


class _Progress:
    def __init__(self, total: int) -> None:
        self.total, self.done, self.failed = total, 0, 0
        self.start = self.last = time.perf_counter()
        self.every = max(1, total // 20)

    def step(self, failed: bool) -> None:
        self.done += 1
        self.failed += failed
        now = time.perf_counter()
        if self.done % self.every and self.done != self.total and now - self.last < PROGRESS_PERIOD_S:
            return
        self.last = now
        rate = self.done / max(now - self.start, 1e-9)
        eta = (self.total - self.done) / rate if rate > 0 else float("inf")
        logger.info("shift: %d/%d parts, %.2f parts/s, ETA %.0f s, %d failed", self.done, self.total, rate, eta,
                    self.failed)


def run_batch(client: object, tasks: Iterable[PartTask], total: int, bases_path: str, history: History,
              options: Options, window: int | None = None,
              on_record: Callable[[PartRecord], None] | None = None) -> BatchSummary:
    """Process ``tasks`` (``total`` of them, for progress) on ``client`` into ``history``; parts the history holds as
    processed are skipped without being read. on_record: called with each record after it is written."""
    from distributed import as_completed

    start = time.perf_counter()
    n_workers = max(1, len(client.scheduler_info().get("workers", {})))
    window = window or 4 * n_workers
    done = history.done()
    pending: dict[object, PartTask] = {}
    queue = iter(tasks)
    progress = _Progress(total)
    skipped = processed = 0
    failed: list[tuple[str, str, str]] = []
    futures = as_completed()

    def submit_more() -> None:
        nonlocal skipped
        while len(pending) < window:
            task = next(queue, None)
            if task is None:
                return
            if task.key in done:
                skipped += 1
                progress.step(False)
                continue
            future = client.submit(process_task, task, bases_path, options, pure=False, retries=1)
            pending[future] = task
            futures.add(future)

    submit_more()
    for future in futures:
        task = pending.pop(future)
        try:
            record = future.result()
        except Exception as error:  # e.g. KilledWorker: recorded as failed, the batch goes on
            record = PartRecord(source=task.source, part_id=task.part_id, message=task.message,
                                stamp_ns=task.stamp_ns, shift=options.shift, status="failed", method=options.method,
                                error=f"{type(error).__name__}: {error}".splitlines()[0])
        future.release()
        if history.add(record):
            processed += 1
        if record.status == "failed":
            failed.append((record.source, record.part_id, record.error))
        progress.step(record.status == "failed")
        if on_record is not None:
            on_record(replace(record, residual=None))
        submit_more()
    seconds = time.perf_counter() - start
    logger.info("shift: %d parts processed (%d failed, %d already in the history) in %.1f s", processed, len(failed),
                skipped, seconds)
    return BatchSummary(total, skipped, processed, tuple(failed), seconds, n_workers)
