"""`hood-decomp ensemble`: generate the simulation ensemble (full factorial + validation) into an HDF5 store."""

from __future__ import annotations

import argparse
import sys
import time

from hood_decomp.cli._common import emit_json
from hood_decomp.errors import EnsembleError

HELP = "generate the simulation ensemble (full factorial + uniform validation) into an HDF5 store"
LOG_FORMAT = "[%(elapsed)7.1f s] %(message)s"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", help="model directory or its model.yaml (needed unless --export)")
    parser.add_argument("--out", required=True, help="ensemble store to write (.h5, schema in docs/ensemble_schema.md)")
    parser.add_argument("--export", metavar="GROUP:INDEX", default=None,
                        help="instead of computing, export one member of the existing store --out (e.g. training:17)")
    parser.add_argument("--field", default=None, help="field file (.vtu) written by --export")
    parser.add_argument("--validation", type=int, default=1400, help="uniform random validation members (1400)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the validation members (0)")
    parser.add_argument("--solver", choices=["embedded", "calculix"], default="embedded",
                        help="embedded shell solver, or CalculiX (ccx) for the unit responses")
    parser.add_argument("--scheduler", default=None,
                        help="Dask scheduler address for CalculiX jobs (default: a local cluster)")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.io.ensemble_store import write_ensemble
    from hood_decomp.io.model_files import load_model

    if args.export is not None:
        return _export(args)
    if args.model is None:
        raise EnsembleError("--model is required to compute an ensemble")
    start = time.perf_counter()
    model = load_model(args.model)
    if args.solver == "embedded":
        from hood_decomp.core.fe.solver import build_solver, reduce_model

        solver = build_solver(model)
        reduced, backend = reduce_model(solver), solver.backend
    else:
        from hood_decomp.core.fe.calculix import reduce_model_calculix

        reduced = reduce_model_calculix(model, scheduler=args.scheduler)
        backend = "ccx"
    summary = write_ensemble(args.out, reduced, skin_surface(model), model.lower, model.upper,
                             n_validation=args.validation, seed=args.seed, solver=args.solver,
                             solver_backend=backend)
    summary["out"] = args.out
    summary["seconds"] = round(time.perf_counter() - start, 2)
    emit_json(summary)
    return 0


def _export(args: argparse.Namespace) -> int:
    from hood_decomp.io.ensemble_store import export_member

    group, _, index = args.export.partition(":")
    if not index.isdigit() or args.field is None:
        raise EnsembleError(f"--export needs GROUP:INDEX (e.g. training:17) and --field OUT.vtu, got {args.export!r}")
    path = export_member(args.out, group, int(index), args.field)
    print(f"wrote {path}", file=sys.stderr)
    return 0
