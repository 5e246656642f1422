"""`hood-decomp estimate`: estimate the parameter states of a field or scan (eqs. 4-5, contact-aware by default)."""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

from hood_decomp.errors import ScanError

HELP = "estimate the parameter states of a field or scan"


def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """--bases and exactly one of --field / --scan (shared with `decompose`)."""
    parser.add_argument("--bases", required=True, type=Path, help="bases file written by `hood-decomp bases`")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--field", type=Path, help="field file (.vtu with point data normal_displacement)")
    source.add_argument("--scan", type=Path, help="scan point cloud (.ply), converted to a field first")
    parser.add_argument("--json", type=Path, default=None, help="write the result as JSON here (default: stdout)")
    parser.add_argument("--min-coverage", type=float, default=0.2,
                        help="smallest fraction of skin nodes the field must cover (default 0.2)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser)
    parser.add_argument("--method", choices=("contact", "pca"), default="contact",
                        help="contact-aware estimator (default) or the paper's PCA estimator")


def load_input(args: argparse.Namespace):
    """(Bases, DisplacementField) from --bases and --field/--scan."""
    from hood_decomp.io.bases import load_bases

    bases = load_bases(args.bases)
    if args.field is not None:
        from hood_decomp.io.fields import read_field

        return bases, read_field(args.field, bases.skin)[0]
    try:
        from_file = importlib.import_module("hood_decomp.cli.scan").field_from_scan_file
    except (ImportError, AttributeError) as error:
        raise ScanError(f"--scan needs the scan-to-field code (hood_decomp.cli.scan.field_from_scan_file and "
                        f"hood_decomp.core.scan.scan_field), not available: {error}") from error
    return bases, from_file(bases.skin, args.scan, min_coverage=args.min_coverage)


def emit(payload: dict, path: Path | None) -> None:
    text = json.dumps(payload, indent=2, allow_nan=False)
    if path is None:
        print(text)
    else:
        path.write_text(text + "\n")
        print(f"wrote {path}", file=sys.stderr)


def _number(value: float) -> float | None:
    """JSON has no NaN: unknown values become null."""
    return None if value != value else float(value)


def estimate_payload(estimate, n_bilateral: int) -> dict:
    """The JSON contract of `estimate` (DESIGN.md; ``lifted`` for the unilateral boundaries), plus within_model and
    method."""
    names = estimate.names
    return {
        "parameters_mm": {n: _number(v) for n, v in zip(names, estimate.values, strict=True)},
        "std_mm": {n: _number(v) for n, v in zip(names, estimate.std, strict=True)},
        "lifted": {n: bool(v) for n, v in zip(names[n_bilateral:], estimate.lifted[n_bilateral:], strict=True)},
        "residual_rms_mm": _number(estimate.residual_rms),
        "residual_max_mm": _number(estimate.residual_max),
        "coverage": _number(estimate.coverage),
        "within_model": bool(estimate.within_model),
        "method": estimate.method,
    }


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.method.bases import estimate_field

    bases, field = load_input(args)
    estimate = estimate_field(bases, field, args.method, args.min_coverage)
    emit(estimate_payload(estimate, bases.pca.n_bilateral_), args.json)
    return 0
