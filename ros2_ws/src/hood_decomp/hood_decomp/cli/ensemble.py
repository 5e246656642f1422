"""`hood-decomp ensemble`: generate the simulation ensemble (full factorial + validation) into an HDF5 store."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from hood_decomp.cli._common import check_output, emit_json, finite, model_inputs, written_whole
from hood_decomp.errors import EnsembleError

HELP = "generate the simulation ensemble (full factorial + uniform validation) into an HDF5 store"
LOG_FORMAT = "[%(elapsed)7.1f s] %(message)s"
#: validation members at most: 100,000 members of the paper's 188,730 skin nodes are 300 GB of float32 3D
#: displacements; 1400 (the paper's) is what the method needs
MAX_VALIDATION = 100_000
#: seconds to wait for a Dask scheduler to answer before refusing its address
SCHEDULER_TIMEOUT_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", help="model directory or its model.yaml (needed unless --export)")
    parser.add_argument("--out", required=True, help="ensemble store to write (.h5, schema in docs/ensemble_schema.md)")
    parser.add_argument("--export", metavar="GROUP:INDEX", default=None,
                        help="instead of computing, export one member of the existing store --out (e.g. training:17)")
    parser.add_argument("--field", default=None, help="field file (.vtu) written by --export")
    parser.add_argument("--validation", type=finite(0, MAX_VALIDATION, integer=True), default=1400,
                        help=f"uniform random validation members (1400; at most {MAX_VALIDATION})")
    parser.add_argument("--seed", type=finite(0, 2**32 - 1, integer=True), default=0,
                        help="seed of the validation members (0)")
    parser.add_argument("--solver", choices=["embedded", "calculix"], default="embedded",
                        help="embedded shell solver, or CalculiX (ccx) for the unit responses")
    parser.add_argument("--scheduler", default=None,
                        help="Dask scheduler address for CalculiX jobs (default: a local cluster)")
    parser.add_argument("--nonlinear", action="store_true",
                        help="geometrically nonlinear members (Green-Lagrange membrane strains) through a reduced "
                             "model built for the ranges (embedded solver only; docs/paper_comparison.md)")
    parser.add_argument("--range", action="append", default=[], metavar="LABEL=MIN:MAX",
                        help="override a parameter's range in mm, e.g. HINGE_Y=-0.5:0.5 (repeatable); on "
                             "hood-paper HINGE_Y +1 mm buckles the hood, so --nonlinear needs it within +-0.5")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.io.ensemble_store import write_ensemble
    from hood_decomp.io.model_files import load_model

    if args.export is not None:
        return _export(args)
    if args.model is None:
        raise EnsembleError("--model is required to compute an ensemble")
    out = check_output(args.out, model_inputs(args.model))
    if args.scheduler is not None:
        if args.solver != "calculix":
            raise EnsembleError("--scheduler is used only with --solver calculix (the embedded solver runs here)")
        _check_scheduler(args.scheduler)
    if args.nonlinear and args.solver != "embedded":
        raise EnsembleError("--nonlinear needs --solver embedded (the nonlinear terms are the embedded shell's)")
    start = time.perf_counter()
    model = load_model(args.model)
    lower, upper = _ranges(model.names, model.lower, model.upper, args.range)
    nonlinear = None
    if args.solver == "embedded":
        from hood_decomp.core.fe.solver import build_solver, reduce_model

        solver = build_solver(model)
        reduced, backend = reduce_model(solver), solver.backend
        if args.nonlinear:
            from hood_decomp.core.fe.reduced_geometric import build_reduced_geometric

            nonlinear = build_reduced_geometric(solver, lower, upper)
    else:
        from hood_decomp.core.fe.calculix import reduce_model_calculix

        reduced = reduce_model_calculix(model, scheduler=args.scheduler)
        backend = "ccx"
    with written_whole(out) as temporary:
        summary = write_ensemble(temporary, reduced, skin_surface(model), lower, upper,
                                 n_validation=args.validation, seed=args.seed, solver=args.solver,
                                 solver_backend=backend, nonlinear=nonlinear)
    summary["out"] = args.out
    summary["seconds"] = round(time.perf_counter() - start, 2)
    emit_json(summary)
    return 0


def _ranges(names: tuple[str, ...], lower: np.ndarray, upper: np.ndarray, overrides: list[str]
            ) -> tuple[np.ndarray, np.ndarray]:
    """The model's ranges (P,) mm with ``--range LABEL=MIN:MAX`` overrides applied."""
    lower, upper = lower.astype(float), upper.astype(float)
    for text in overrides:
        label, _, span = text.partition("=")
        low, _, high = span.partition(":")
        try:
            values = float(low), float(high)
        except ValueError:
            values = (float("nan"), float("nan"))
        if label not in names or not all(np.isfinite(values)) or not values[0] < values[1]:
            raise EnsembleError(f"--range {text[:80]!r}: expected LABEL=MIN:MAX with LABEL among {list(names)} "
                                "and finite MIN < MAX (mm)")
        lower[names.index(label)], upper[names.index(label)] = values
    return lower, upper


def _export(args: argparse.Namespace) -> int:
    from hood_decomp.io.ensemble_store import export_member

    group, _, index = args.export.partition(":")
    if not index.isdigit() or args.field is None:
        raise EnsembleError(f"--export needs GROUP:INDEX (e.g. training:17) and --field OUT.vtu, got "
                            f"{args.export[:80]!r}")
    out = check_output(args.field, [args.out], "--field")
    with written_whole(out) as temporary:
        export_member(args.out, group, int(index), temporary)
    print(f"wrote {out}", file=sys.stderr)
    return 0


def _check_scheduler(address: str) -> None:
    """Refuse a Dask scheduler address that is malformed or does not accept a connection within
    :data:`SCHEDULER_TIMEOUT_S`, before any work (dask itself would wait 30 s and end in an OSError)."""
    import socket

    from distributed.comm import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as error:
        raise EnsembleError(f"--scheduler {address[:80]!r}: not a Dask scheduler address (expected "
                            "tcp://HOST:PORT)") from error
    if scheme not in ("tcp", "tls") or not port:
        raise EnsembleError(f"--scheduler {address[:80]!r}: expected tcp://HOST:PORT or tls://HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=SCHEDULER_TIMEOUT_S).close()
    except OSError as error:
        raise EnsembleError(f"--scheduler {address[:80]!r}: no scheduler answers there within "
                            f"{SCHEDULER_TIMEOUT_S:g} s ({error.strerror or error})") from error
