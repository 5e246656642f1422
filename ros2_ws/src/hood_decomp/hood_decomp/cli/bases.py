"""`hood-decomp bases`: build the PCA and hierarchical bases from an ensemble."""

from __future__ import annotations

import argparse

from hood_decomp.cli._pending import add_passthrough, not_built

HELP = "build the PCA and hierarchical bases from an ensemble (not built yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_passthrough(parser)


def run(args: argparse.Namespace) -> int:
    return not_built("bases", 4)
