"""`hood-decomp estimate`: estimate the parameter states of a field or scan."""

from __future__ import annotations

import argparse

from hood_decomp.cli._pending import add_passthrough, not_built

HELP = "estimate the parameter states of a field or scan (not built yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_passthrough(parser)


def run(args: argparse.Namespace) -> int:
    return not_built("estimate", 4)
