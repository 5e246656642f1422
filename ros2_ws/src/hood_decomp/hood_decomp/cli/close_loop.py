"""`hood-decomp close-loop`: find, add and report an effect the model lacks (docs/close_loop.md).

Writes DIR/close_loop.json (residual before/after, effect found, magnitude, parameter errors where --truth gives the
truth), DIR/residual_before_<i>.png, DIR/residual_after_<i>.png, DIR/before_after.png and, when an effect was
added, the rebuilt bases DIR/bases_closed_loop.h5 (usable with `estimate` and `decompose`).
Each --field and each --scan is one part, except scans given with --scanner-pose: those are the views of one part,
fused into one field (every view then needs a pose).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from hood_decomp.cli._common import (
    add_bases,
    add_inputs,
    add_reference,
    apply_reference,
    check_output,
    finite,
    input_paths,
    marker_checks_or_none,
    model_inputs,
    read_fields,
    write_json,
    written_whole_directory,
)
from hood_decomp.errors import FieldError, ModelIdMismatchError
from hood_decomp.io.json_values import loads_strict
from hood_decomp.io.small_files import read_small_file

HELP = "find, add and report an effect the model lacks (residual -> candidate effects -> new parameter -> bases)"
LOG_FORMAT = "close-loop: %(message)s"
#: largest --truth file read (label -> value per field: a few kB)
MAX_TRUTH_BYTES = 1 << 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model directory or its model.yaml (its "
                        "optional 'candidates:' list adds user candidate effects)")
    add_bases(parser)
    add_inputs(parser, repeatable=True)
    add_reference(parser)
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--truth", type=Path, default=None, help="JSON: label -> true value (mm; N for a force "
                        "effect) for all fields, or a list of such objects, one per field")
    parser.add_argument("--ensemble", type=Path, default=None, help="ensemble store of the bases: its training "
                        "members are reused (default: solved again from the bases' reduced model)")
    parser.add_argument("--alpha", type=finite(0.0, 0.5, low_open=True), default=0.01,
                        help="significance level of the tests (default 0.01)")
    parser.add_argument("--noise-mm", type=finite(0.0, 10.0, low_open=True), default=None,
                        help="scan noise (mm, one sigma) of fields that do not state their own (default: "
                        "hood_decomp.core.method.residual.DEFAULT_NOISE_MM)")
    parser.add_argument("--max-effects", type=finite(1, 2, integer=True), default=2,
                        help="effects added at most: 1 (one candidate) or 2 (default: a pair of candidates may "
                        "explain one missing effect)")
    parser.add_argument("--method", choices=("contact", "pca"), default="contact",
                        help="estimator of the before/after estimates (tracing is always contact-aware)")


def _read_truth(path: Path | None) -> object:
    """The --truth JSON document (None without --truth), read as every small input is (a regular file, at most
    MAX_TRUTH_BYTES): before the fields, so a bad one is refused at once."""
    if path is None:
        return None
    try:
        return loads_strict(read_small_file(path, MAX_TRUTH_BYTES, FieldError, "--truth").decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise FieldError(f"--truth {path}: not a readable JSON file: {' '.join(str(error).split())[:120]}") from error


def _truth_values(document: object, path: Path | None, n_fields: int) -> list[dict[str, float]] | None:
    """The --truth ``document`` as label -> value (mm) per field, checked."""
    if path is None:
        return None
    entries = document if isinstance(document, list) else [document] * n_fields
    if len(entries) != n_fields or not all(isinstance(e, dict) for e in entries):
        raise FieldError(f"--truth {path}: expected an object label -> value or a list of {n_fields} such objects")
    try:
        truth = [{str(k): float(v) for k, v in e.items()} for e in entries]
    except (TypeError, ValueError) as error:
        raise FieldError(f"--truth {path}: values must be numbers: {error}") from error
    if not all(math.isfinite(v) for e in truth for v in e.values()):
        raise FieldError(f"--truth {path}: values must be finite numbers")
    return truth


def _table(payload: dict) -> str:
    lines = [f"status: {payload['status']}: {payload['message']}"]
    for trace in payload["traces"]:
        lines.append("  candidate             explained  adj. p      magnitude")
        for row in trace["ranking"]:
            magnitude = ", ".join("nan" if v is None else f"{v:+.4g}" for v in row["magnitude"])
            explained = row["explained"] if row["explained"] is not None else float("nan")
            lines.append(f"  {row['name']:<20} {100 * explained:8.1f} %  {row['p_adjusted']:<10.3g}  "
                         f"{magnitude} {row['unit']}")
        lines.append(f"  -> {trace['reason']}")
    after = payload["residual_rms_after_mm"] or [None] * len(payload["residual_rms_before_mm"])
    for i, (rms, rms_after) in enumerate(zip(payload["residual_rms_before_mm"], after, strict=True)):
        lines.append(f"  field {i}: residual RMS {rms:.4g} mm -> " + ("(nothing added)" if rms_after is None
                                                                      else f"{rms_after:.4g} mm"))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.fe.solver import build_solver
    from hood_decomp.core.loop.candidates import candidate_fields, enumerate_candidates
    from hood_decomp.core.loop.close_loop import close_loop
    from hood_decomp.core.method.residual import DEFAULT_NOISE_MM
    from hood_decomp.io.bases import load_bases, save_bases
    from hood_decomp.io.close_loop_report import close_loop_report
    from hood_decomp.io.model_files import load_model_with_candidates
    from hood_decomp.plots.close_loop import plot_before_after, plot_residual_maps

    inputs = [*model_inputs(args.model), args.bases, *input_paths(args),
              *(p for p in (args.truth, args.ensemble, args.reference) if p is not None)]
    check_output(args.out, inputs, directory=True, writes=["close_loop.json", "bases_closed_loop.h5"])
    truth_document = _read_truth(args.truth)
    model, user_candidates = load_model_with_candidates(args.model)
    bases = load_bases(args.bases)
    if model.model_id != bases.model_id:
        raise ModelIdMismatchError(f"model {args.model} has model_id {model.model_id!r}, bases {args.bases} "
                                   f"{bases.model_id!r}: build the bases from this model")
    checks: list[dict] = []
    fields = apply_reference(args, bases, read_fields(args.inputs, bases.skin, args.min_coverage,
                                                      args.scanner_poses, marker_std_mm=args.marker_std_mm,
                                                      marker_checks=checks))
    truth = _truth_values(truth_document, args.truth, len(fields))
    ensemble = None
    if args.ensemble is not None:
        from hood_decomp.io.ensemble_store import load_ensemble

        ensemble = load_ensemble(args.ensemble, group="training")
    candidates = candidate_fields(build_solver(model), enumerate_candidates(model, user_candidates))
    result = close_loop(bases, fields, candidates, ensemble=ensemble, alpha=args.alpha,
                        default_noise_mm=DEFAULT_NOISE_MM if args.noise_mm is None else args.noise_mm,
                        max_effects=args.max_effects, method=args.method, min_coverage=args.min_coverage)
    payload = close_loop_report(result, truth)
    payload["inputs"] = [str(path) for _, path in args.inputs]
    payload["candidates"] = list(candidates.names)
    payload["candidates_without_effect"] = list(candidates.dropped)
    payload["marker_noise_checks"] = marker_checks_or_none(args, checks)
    with written_whole_directory(args.out) as directory:
        figures = plot_residual_maps(bases.skin, result, directory)
        figures.append(plot_before_after(result, directory / "before_after.png", truth))
        payload["figures"] = [str(p.name) for p in figures]
        if result.bases_after is not None:
            save_bases(directory / "bases_closed_loop.h5", result.bases_after)
            payload["bases_after"] = "bases_closed_loop.h5"
        write_json(directory / "close_loop.json", payload)
    print(_table(payload))
    print(f"wrote {args.out / 'close_loop.json'}", file=sys.stderr)
    return 0
