"""`hood-decomp decompose`: contributions of the hierarchical effects to a field (paper steps 1-7, eqs. 6-8)."""

from __future__ import annotations

import argparse
from pathlib import Path

from hood_decomp.cli._common import (
    add_bases,
    add_inputs,
    add_json,
    add_reference,
    check_json,
    check_output,
    emit_json,
    finite,
    marker_checks_or_none,
    read_bases_and_field,
)

HELP = "decompose a field or scan into effects with contribution plots"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bases(parser)
    add_inputs(parser)
    add_json(parser)
    add_reference(parser)
    parser.add_argument("--plots", type=Path, default=None, help="directory for the PNG contribution plots")
    parser.add_argument("--method", choices=("contact", "pca"), default="contact",
                        help="estimator of step 2 that selects the effect subset (default contact)")
    parser.add_argument("--min-share", type=finite(0.0, 1.0, low_open=False), default=0.02,
                        help="coarsening: drop effects contributing less than this fraction (default 0.02)")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.method.bases import decompose_field, estimate_field

    inputs = check_json(args)
    if args.plots is not None:
        check_output(args.plots, inputs, "--plots", directory=True)
    checks: list[dict] = []
    bases, field = read_bases_and_field(args, marker_checks=checks)
    estimate = estimate_field(bases, field, args.method, args.min_coverage)
    result = decompose_field(bases, field, estimate, min_share=args.min_share, min_coverage=args.min_coverage)
    payload = {
        "effects": [{"name": e.name, "parameters": list(e.parameters), "share": e.share} for e in result.effects],
        "reconstruction_rms_mm": result.reconstruction_rms,
        # the one within-model test, on the estimate that chose the effects: a part the model does not explain
        # has no trustworthy decomposition either
        "within_model": estimate.within_model,
        "within_model_p_value": estimate.check.p_value,
        "marker_noise_checks": marker_checks_or_none(args, checks),
    }
    if args.plots is not None:
        from hood_decomp.plots.method import plot_contributions

        payload["plots"] = [str(p) for p in plot_contributions(bases.skin, result, args.plots)]
    emit_json(payload, args.json)
    return 0
