"""Shared body of verbs that are not built yet: say so plainly instead of pretending."""

from __future__ import annotations

import argparse
import sys


def not_built(verb: str, issue: int) -> int:
    print(f"hood-decomp {verb}: not built yet (tracked in issue {issue}); nothing was done.", file=sys.stderr)
    return 3


def add_passthrough(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("rest", nargs=argparse.REMAINDER, help="arguments of the verb once it exists")
