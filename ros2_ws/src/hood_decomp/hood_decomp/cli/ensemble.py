"""`hood-decomp ensemble`: generate the simulation ensemble (full factorial + validation)."""

from __future__ import annotations

import argparse

from hood_decomp.cli._pending import add_passthrough, not_built

HELP = "generate the simulation ensemble (full factorial + validation) (not built yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_passthrough(parser)


def run(args: argparse.Namespace) -> int:
    return not_built("ensemble", 3)
