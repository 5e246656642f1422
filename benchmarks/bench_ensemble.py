"""Benchmark: hood model -> factorised embedded solver -> reduced model -> 729 + 1400 member ensemble on disk.

Each resolution runs in its own process (so its peak memory is its own). For comparison, one CalculiX job (the load
case) is timed at the same resolution; "ccx x runs" is that time multiplied by the 2129 members a direct
(one run per member) CalculiX ensemble would need, as a lower bound (a real contact run with buffers needs
nonlinear iterations), and by the 1 + B + S unit-response runs of the reduced CalculiX route.

Usage: PYTHONPATH=ros2_ws/src/hood_decomp .venv/bin/python benchmarks/bench_ensemble.py [--resolutions default paper]
       [--ccx] [--validation 1400]
Prints a table and writes benchmarks/out/bench_ensemble.json.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def worker(resolution: str, validation: int, with_ccx: bool) -> dict[str, object]:
    from hood_decomp.core.fe.ensemble import contact_counts
    from hood_decomp.core.fe.hood_preset import build_hood
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.io.ensemble_store import load_ensemble, write_ensemble

    row: dict[str, object] = {"resolution": resolution}
    start = time.perf_counter()
    model = build_hood(resolution)
    row["model_s"] = time.perf_counter() - start
    row["nodes"] = len(model.nodes)
    row["skin_nodes"] = len(model.skin_nodes)
    row["dof"] = 6 * len(model.nodes)
    t = time.perf_counter()
    solver = build_solver(model)
    row.update(solver.timings)
    row["backend"] = solver.backend
    t2 = time.perf_counter()
    reduced = reduce_model(solver)
    row["reduce_s"] = time.perf_counter() - t2
    row["pad_springs"] = len(reduced.k)
    row["solver_total_s"] = time.perf_counter() - t
    skin = skin_surface(model)
    n_bilateral, n_springs = reduced.n_bilateral, len(reduced.k)
    del solver
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "ensemble.h5"
        t = time.perf_counter()
        summary = write_ensemble(path, reduced, skin, model.lower, model.upper, n_validation=validation)
        row["members_s"] = time.perf_counter() - t
        row["store_mb"] = path.stat().st_size / 1e6
        row["members"] = 729 + validation
        row["training_pad_contact"] = summary["training"]["pad_contact"]
        training = load_ensemble(path, "training")
        counts = [contact_counts(training.contact_fraction[:, u]) for u in range(training.contact_fraction.shape[1])]
        row["per_pad_contact"] = dict(zip(training.names[training.n_bilateral:], counts, strict=True))
    row["total_s"] = time.perf_counter() - start
    row["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    if with_ccx:
        from hood_decomp.core.fe.calculix import ccx_executable, load_cases, run_job, write_deck

        if ccx_executable() is not None:
            cases, constrained = load_cases(model, pad_lattice=1)
            with tempfile.TemporaryDirectory() as directory:
                deck = write_deck(model, cases[0], constrained, Path(directory) / "deck.inp").read_text()
                t = time.perf_counter()
                run_job(deck, "load", len(model.nodes), directory)
                row["ccx_run_s"] = time.perf_counter() - t
            row["ccx_direct_ensemble_s"] = row["ccx_run_s"] * row["members"]
            row["ccx_reduced_route_s"] = row["ccx_run_s"] * (1 + n_bilateral + n_springs)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", nargs="+", default=["default"])
    parser.add_argument("--validation", type=int, default=1400)
    parser.add_argument("--ccx", action="store_true", help="also time one CalculiX run per resolution")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.validation, args.ccx)))
        return 0
    rows = []
    for resolution in args.resolutions:
        command = [sys.executable, __file__, "--worker", resolution, "--validation", str(args.validation)]
        command += ["--ccx"] if args.ccx else []
        print(f"running {resolution} ...", file=sys.stderr, flush=True)
        result = subprocess.run(command, capture_output=True, text=True, check=False)
        if result.returncode != 0:
            print(result.stderr, file=sys.stderr)
            return 1
        rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
    header = ("resolution", "skin_nodes", "dof", "assembly_s", "factorisation_s", "reduce_s", "members_s", "total_s",
              "peak_rss_gb", "ccx_run_s", "ccx_direct_ensemble_s")
    print(" | ".join(header))
    for row in rows:
        print(" | ".join(f"{row.get(h, float('nan')):.1f}" if isinstance(row.get(h), float) else str(row.get(h, "-"))
                         for h in header))
    out = Path(__file__).parent / "out" / "bench_ensemble.json"
    out.parent.mkdir(exist_ok=True)
    # keep rows of resolutions not run this time (paper is run separately, once)
    previous = json.loads(out.read_text()) if out.is_file() else []
    merged = [r for r in previous if r["resolution"] not in args.resolutions] + rows
    out.write_text(json.dumps(merged, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
