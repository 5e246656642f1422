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
import os
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


#: One-shot verbs: what ``run`` computes is small linear algebra beside the scan path's own threads, and when it
#: returns every output is written and closed (files through ``written_whole``, JSON on stdout) with no child process,
#: server, cluster or open file left behind. :func:`entry` runs them with one BLAS thread and without the
#: interpreter's teardown.
_ONE_SHOT_VERBS = frozenset({"estimate"})
#: Verbs whose linear algebra is many small BLAS calls (a field's estimate: N x K products, K x K solves), run with
#: one BLAS thread unless OPENBLAS_NUM_THREADS is set: with OpenBLAS' default two the idle worker spins between calls,
#: and beside other work on the cores the demo's validation of 1,400 x 3 estimates took 608 s instead of 114 s, its
#: close-the-loop step (close-loop's tracing estimates) 54 s instead of 29 s (load 3-4.8, session 18; one field's
#: contact-aware estimate 27-34 ms with one thread, 100-650 ms with two). The shift's Dask workers get one already.
_ONE_BLAS_THREAD_VERBS = _ONE_SHOT_VERBS | {"demo", "close-loop"}


def entry() -> NoReturn:
    """The ``hood-decomp`` program: :func:`main` on ``sys.argv``, then exit with its status.

    For a verb of :data:`_ONE_SHOT_VERBS` (issue 19: a one-off `estimate --scan` at paper resolution, 1M points; the
    first point also for every verb of :data:`_ONE_BLAS_THREAD_VERBS`):
    - OpenBLAS gets one thread unless OPENBLAS_NUM_THREADS is set: its idle workers spin between the many small BLAS
      calls (3 x 3 solves, N x K projections) and took 0.3 s of the process's 1.4 s user CPU on the 2 cores the
      scan path's own threads need. Set before numpy is imported (nothing above this imports it).
    - The process ends by ``os._exit`` once stdout and stderr are flushed and logging is shut down: the
      interpreter's teardown of a 0.7 GB process (freeing every array and module, joining idle pool threads) took
      0.15-0.35 s and writes nothing. Every output is complete and closed by then (written_whole has renamed it into
      place; stdout is flushed here) and the status is main's; when a flush fails (a closed pipe) the normal exit
      reports it instead.
    """
    argv = sys.argv[1:]
    verb = next((a for a in argv if not a.startswith("-")), None)
    one_shot = verb in _ONE_SHOT_VERBS
    if verb in _ONE_BLAS_THREAD_VERBS:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    status = main(argv)
    if one_shot:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            logging.shutdown()
        except (OSError, ValueError):
            sys.exit(status)
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":
    entry()
