"""`hood-decomp shift BAGS_OR_DIRS... --bases B --out DIR [--scheduler ADDR] [--workers N] [--history DB]
[--model M] [--reference REF.json]`:
a shift of parts on Dask into a results history, then its statistical process control, recurring residuals and
report (OUT/index.html, OUT/shift.json, OUT/history.csv)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from hood_decomp.cli._common import add_reference

HELP = "process a shift of parts (bags, scans, fields) on Dask into a results history and a shift report"
LOG_FORMAT = "hood-decomp shift %(asctime)s: %(message)s"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", type=Path, metavar="BAGS_OR_DIRS",
                        help="rosbag2 directories (scans on their sidecar's topic), .vtu fields, .ply scans, or "
                        "directories holding them")
    parser.add_argument("--bases", required=True, type=Path, help="bases file written by `hood-decomp bases`")
    parser.add_argument("--out", required=True, type=Path, help="directory for the report, shift.json, history.csv")
    parser.add_argument("--scheduler", default=None, metavar="ADDR",
                        help="address of a running dask scheduler (default: a local cluster)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes of the local cluster (default 2)")
    parser.add_argument("--history", type=Path, default=None,
                        help="results history (SQLite; default OUT/history.sqlite); appended to, parts already in it "
                        "are not processed again")
    parser.add_argument("--method", choices=("contact", "pca"), default="contact", help="estimator (default contact)")
    parser.add_argument("--min-coverage", type=float, default=0.2, help="smallest seen fraction of the skin")
    parser.add_argument("--alpha", type=float, default=0.01, help="false-alarm rate of the within-model test")
    parser.add_argument("--baseline", type=int, default=50,
                        help="parts (in time order) that set the control limits (default 50)")
    parser.add_argument("--label", default=None, help="label of this run in the history (default: its start time)")
    parser.add_argument("--model", type=Path, default=None,
                        help="the part model (model.yaml): recurring residuals are traced to its FE candidate effects "
                        "first; without it every recurring mode is offered as a measured effect")
    add_reference(parser)  # the cell's reference for every part; the history records it per part


def run(args: argparse.Namespace) -> int:
    from hood_decomp.errors import FieldError, HistoryError
    from hood_decomp.io.bases import load_bases
    from hood_decomp.io.history import History
    from hood_decomp.shift.part import Options
    from hood_decomp.shift.report import analyse_and_report
    from hood_decomp.shift.runner import dask_client, run_batch
    from hood_decomp.shift.sources import find_sources, iter_tasks

    if args.workers < 1:
        raise FieldError(f"--workers must be >= 1, got {args.workers}")
    bases = load_bases(args.bases)  # refused here, before a cluster starts, when it is no bases file
    reference = ""
    if args.reference is not None:  # likewise: a reference that does not serve these bases is refused now
        from hood_decomp.io.calibration_files import read_reference

        reference = read_reference(args.reference.resolve(), bases, args.min_coverage).path
    sources = find_sources(args.inputs)
    total = sum(s.count for s in sources)
    args.out.mkdir(parents=True, exist_ok=True)
    history_path = args.history or args.out / "history.sqlite"
    if history_path.exists() and history_path.is_dir():
        raise HistoryError(f"--history {history_path} is a directory")
    options = Options(method=args.method, min_coverage=args.min_coverage, alpha=args.alpha,
                      shift=args.label or time.strftime("%Y-%m-%dT%H:%M:%S"), reference=reference)
    with History(history_path) as history:
        with dask_client(args.scheduler, args.workers) as client:
            summary = run_batch(client, iter_tasks(sources), total, str(args.bases.resolve()), history, options)
        report = analyse_and_report(history, [str(s.path) for s in sources], bases, args.out, summary,
                                    baseline=args.baseline, alpha=args.alpha, model_path=args.model)
    print(f"hood-decomp shift: {summary.total} parts, {summary.processed} processed, {summary.skipped} already in "
          f"the history, {len(summary.failed)} failed; report written to {report.resolve()}", file=sys.stderr)
    return 1 if summary.failed else 0
