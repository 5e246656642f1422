"""`hood-decomp simulate`: one forward FE solve of a boundary setting."""

from __future__ import annotations

import argparse

from hood_decomp.cli._pending import add_passthrough, not_built

HELP = "one forward FE solve of a boundary setting (not built yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_passthrough(parser)


def run(args: argparse.Namespace) -> int:
    return not_built("simulate", 3)
