"""`hood-decomp scan`: synthesise a structured-light scan of a displaced part."""

from __future__ import annotations

import argparse

from hood_decomp.cli._pending import add_passthrough, not_built

HELP = "synthesise a structured-light scan of a displaced part (not built yet)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_passthrough(parser)


def run(args: argparse.Namespace) -> int:
    return not_built("scan", 5)
