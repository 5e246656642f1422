"""`hood-decomp decompose`: decompose a field or scan into per-effect contributions."""

from __future__ import annotations

import argparse

from hood_decomp.cli._pending import add_passthrough, not_built

HELP = "decompose a field or scan into per-effect contributions (not built yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_passthrough(parser)


def run(args: argparse.Namespace) -> int:
    return not_built("decompose", 4)
