"""`hood-decomp demo`: the whole pipeline on the built-in hood, ending in a report a person can open."""

from __future__ import annotations

import argparse
import pathlib
import sys

from hood_decomp.cli._common import check_output, finite

HELP = "run the whole pipeline on the built-in hood and write DIR/index.html"
LOG_FORMAT = "[demo %(asctime)s] %(message)s"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/demo"), help="report directory")
    parser.add_argument("--preset", choices=("hood", "hood-paper"), default="hood",
                        help="built-in model (default: hood; hood-paper: the paper's boundary physics)")
    parser.add_argument("--resolution", choices=("coarse", "default", "paper"), default="default",
                        help="hood mesh resolution (default: default)")
    parser.add_argument("--validation", type=finite(0, 100_000, integer=True), default=1400,
                        help="validation members (default 1400)")
    parser.add_argument("--scan-points", type=finite(1000, 50_000_000, integer=True), default=1_000_000,
                        help="points per synthetic scan")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.demo.run import DemoConfig, run_demo

    check_output(args.out, (), directory=True, parents=True)

    path = run_demo(DemoConfig(out=args.out, preset=args.preset, resolution=args.resolution,
                               n_validation=args.validation, scan_points=args.scan_points))
    print(f"hood-decomp demo: report written to {path.resolve()}", file=sys.stderr)
    return 0
