"""The ``hood-decomp`` command line.

Each verb lives in its own module ``hood_decomp.cli.<verb>`` exposing ``HELP`` (one line), ``add_arguments(parser)``
and ``run(args) -> int``, and optionally ``LOG_FORMAT``: how its progress lines look (a :mod:`logging` format; the
default is the bare message). Modules are imported lazily so ``--help`` stays fast and a verb only pays for what it
uses; what verbs share is in ``cli._common``, and verbs never import each other.

Progress: the package's modules log to ``logging.getLogger(__name__)``; while a verb runs, one handler on the
``hood_decomp`` logger prints INFO and above to stderr in the verb's ``LOG_FORMAT``.
Bad input (any :class:`~hood_decomp.errors.HoodDecompError`, a usage error, or an OSError of a read or write) ends in
one line on stderr and exit status 2; numeric options are finite and in range (``_common.finite``), and outputs are
checked before any work and written whole (``_common.check_output``, ``written_whole``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import NoReturn

from hood_decomp import __version__
from hood_decomp.errors import HoodDecompError

# verb -> module name; the order is the order of --help.
VERBS: dict[str, str] = {
    "model": "model",
    "simulate": "simulate",
    "ensemble": "ensemble",
    "bases": "bases",
    "estimate": "estimate",
    "decompose": "decompose",
    "close-loop": "close_loop",
    "calibrate": "calibrate",
    "scan": "scan",
    "replay": "replay",
    "shift": "shift",
    "launch": "launch",
    "demo": "demo",
}


class _Parser(argparse.ArgumentParser):
    """argparse with the verbs' error contract: a usage error is one line on stderr and exit status 2 (``--help``
    shows the usage)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())}\n")


def _build_parser(argv: Sequence[str]) -> argparse.ArgumentParser:
    parser = _Parser(
        prog="hood-decomp",
        description="Decompose scanned deviations of a sheet-metal assembly into boundary effects "
        "(Claus & Hamann). Lengths in millimetres.",
    )
    parser.add_argument("--version", action="version", version=f"hood-decomp {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    sub.required = True
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for verb, module_name in VERBS.items():
        if wanted is not None and wanted != verb:
            # Only the chosen verb's module is imported; the others get a bare entry for the verb list.
            sub.add_parser(verb)
            continue
        module = importlib.import_module(f"hood_decomp.cli.{module_name}")
        verb_parser = sub.add_parser(verb, help=module.HELP, description=module.HELP)
        module.add_arguments(verb_parser)
        verb_parser.set_defaults(_run=module.run, _log_format=getattr(module, "LOG_FORMAT", "%(message)s"))
    return parser


class _ProgressFormatter(logging.Formatter):
    """A format that may also use ``%(elapsed)s``: seconds since the verb started; ``%(asctime)s`` is HH:MM:SS."""

    def __init__(self, fmt: str) -> None:
        super().__init__(fmt, datefmt="%H:%M:%S")
        self._start = time.time()

    def format(self, record: logging.LogRecord) -> str:
        record.elapsed = record.created - self._start
        return super().format(record)


@contextmanager
def _progress_to_stderr(fmt: str) -> Iterator[None]:
    """While the block runs, INFO and above of every hood_decomp logger go to stderr in ``fmt``."""
    package = logging.getLogger("hood_decomp")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_ProgressFormatter(fmt))
    level = package.level
    package.addHandler(handler)
    package.setLevel(logging.INFO)
    try:
        yield
    finally:
        package.removeHandler(handler)
        package.setLevel(level)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser(argv)
    args = parser.parse_args(argv)
    try:
        with _progress_to_stderr(args._log_format):
            return int(args._run(args))
    except HoodDecompError as error:
        print(f"hood-decomp {args.verb}: error: {' '.join(str(error).split())}", file=sys.stderr)
        return 2
    except OSError as error:  # the machine refused a read or write the checks could not foresee (disk full, ...)
        where = f": {error.filename}" if error.filename else ""
        print(f"hood-decomp {args.verb}: error: {error.strerror or error}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"hood-decomp {args.verb}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
