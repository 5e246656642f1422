"""`hood-decomp model`: write a part model (model.yaml + mesh) from a built-in preset."""

from __future__ import annotations

import argparse

from hood_decomp.cli._pending import add_passthrough, not_built

HELP = "write a part model (model.yaml + mesh) from a built-in preset (not built yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_passthrough(parser)


def run(args: argparse.Namespace) -> int:
    return not_built("model", 3)
