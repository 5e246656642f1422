"""The cost of one estimate of the built-in hood, phase by phase (issue 15: estimation at paper scale under 5 ms).

Unlike ``bench_gls.py`` (a toy that isolates the generalised fit), this times the product's path on the real hood:
``estimate_field`` on a bases file, with the contact-aware estimator's column per pad spring, the model spread of the
gate and a scan's reading. Bases: ``--bases B.h5`` (a file `hood-decomp bases` wrote), else the built-in hood at
``--resolution`` built in memory (tests/conftest.py ``_hood_case``; paper resolution takes about 10 GB and 10
minutes: run it under the memory lock) and written to ``--store DIR`` when given, which a later run then reads.

Fields: ``--fields`` members of the model (random states over the declared ranges) with white noise of a stated
error model, and ``--scans`` synthetic scans of such members (the synthetic scanner's points, markers recovered,
holes) through the scan step with its error model. Each field is estimated once to warm up, then timed
``--repeat`` times (CPU, one BLAS thread), with each ``--coarsen`` stride (the paper's coarsening of the input
field, ``estimate_field``'s ``coarsen``; "auto" coarsens the paper-resolution hood to a quarter of its nodes); the
phases are timed by wrapping the functions that make them:

- ``reading``: a scan's slide and reading bias taken out (``bases.node_field``);
- ``weight``: the weight and the test made before the fit (``fit_weight``), with its weighted Gram inside;
- ``test``: the within-model test (``ResidualTest.check``), inside ``weight`` where the fit does not look at it;
- ``grams``: every weighted Gram (``weighted_gram``), inside the two above;
- ``spread``: the model's physical factors (``ContactEstimator._factor_effects``);
- ``whole``: the whole ``estimate_field``.

Prints a table of medians (CPU ms per estimate) and writes benchmarks/out/estimate.json. From the repository root:
    OPENBLAS_NUM_THREADS=1 scripts/with-env python benchmarks/bench_estimate.py --resolution paper --store DIR
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_uncertainty import POINTS  # noqa: E402  (scan points on the skin per resolution)

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.method import bases as bases_module  # noqa: E402
from hood_decomp.core.method import contact_estimation, estimation, residual  # noqa: E402
from hood_decomp.core.method.bases import estimate_field  # noqa: E402
from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator  # noqa: E402
from hood_decomp.core.types import DisplacementField, FieldErrorModel  # noqa: E402
from hood_decomp.io.bases import load_bases, save_bases  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402
from tests.conftest import _hood_case  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "estimate.json"
PHASES = ("reading", "weight", "test", "grams", "spread")


def log(message: str) -> None:
    print(f"[bench_estimate] {message}", file=sys.stderr, flush=True)


def read_bases(args: argparse.Namespace):
    """The bases of the run: --bases, else --store's file when it exists, else built (and stored when asked)."""
    path = args.bases or (None if args.store is None else args.store / "bases.h5")
    if path is not None and path.exists():
        log(f"reading {path}")
        return load_bases(path)
    log(f"building the {args.resolution} hood, its ensemble and bases")
    with tempfile.TemporaryDirectory() as tmp:
        case = _hood_case(args.resolution, Path(tmp))
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_bases(path, case.bases)
        return load_bases(path)  # as a product reads it (the prepared scan skin registered on loading)
    return case.bases


@contextlib.contextmanager
def phase_clocks():
    """CPU seconds spent in each phase's functions (:data:`PHASES`), accumulated while the context is open."""
    spent: dict[str, float] = defaultdict(float)

    def clocked(name, fn):
        @functools.wraps(fn)
        def run(*a, **k):
            start = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.process_time() - start
        return run

    targets = [(bases_module, "node_field", "reading"), (contact_estimation, "fit_weight", "weight"),
               (estimation, "fit_weight", "weight"), (residual.ResidualTest, "check", "test"),
               (estimation, "weighted_gram", "grams"), (residual, "weighted_gram", "grams"),
               (contact_estimation.ContactEstimator, "_factor_effects", "spread")]
    with contextlib.ExitStack() as stack:
        for owner, attr, name in targets:
            stack.enter_context(mock.patch.object(owner, attr, clocked(name, getattr(owner, attr))))
        yield spent


def timed(bases, fields: list[DisplacementField], method: str, repeat: int, strides: list[int | str]
          ) -> dict[int | str, dict[str, float]]:
    """Per coarsening stride, median CPU ms per estimate of ``fields`` (each estimated once untimed first), whole (a
    run of its own) and per phase. The strides take turns field by field, so that a shared machine's load falls on
    them alike, each repeated on its field in a row as a node estimates with one stride."""
    rows: dict[int | str, list[dict]] = {stride: [] for stride in strides}
    for field in fields:
        for stride in strides:
            estimate_field(bases, field, method, coarsen=stride)
            for _ in range(repeat):
                start = time.process_time()  # unwrapped: the phases' clocks cost ~1 ms at paper resolution
                estimate_field(bases, field, method, coarsen=stride)
                whole = time.process_time() - start
                with phase_clocks() as spent:
                    estimate_field(bases, field, method, coarsen=stride)
                rows[stride].append({"whole": whole, **{name: spent[name] for name in PHASES}})
    return {stride: {name: 1e3 * float(np.median([row[name] for row in judged])) for name in ("whole", *PHASES)}
            for stride, judged in rows.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=tuple(POINTS), default="paper")
    parser.add_argument("--bases", type=Path, default=None, help="a bases file to time (else the built-in hood)")
    parser.add_argument("--store", type=Path, default=None, help="keep the built bases in DIR/bases.h5 and reuse it")
    parser.add_argument("--fields", type=int, default=6, help="noise fields (white, stated error model)")
    parser.add_argument("--scans", type=int, default=4, help="synthetic scans through the scan step")
    parser.add_argument("--repeat", type=int, default=3, help="timed estimates per field")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--coarsen", nargs="+", default=["auto"],
                        help="coarsening strides to time (estimate_field's coarsen: 'auto' or an integer >= 1)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    strides = [value if value == "auto" else int(value) for value in args.coarsen]
    bases = read_bases(args)
    skin, reduced = bases.skin, bases.reduced_model
    rng = np.random.default_rng(args.seed)
    lo, hi = bases.pca.lower_, bases.pca.upper_
    members = solve_members(reduced, rng.uniform(lo, hi, (args.fields + args.scans, lo.size)))
    noise_fields = []
    for k in range(args.fields):
        sigma = rng.uniform(0.01, 0.05)
        values = members.normal_displacement[k] + rng.normal(0.0, sigma, skin.n_nodes)
        noise_fields.append(DisplacementField(skin.model_id, values, 1.0, float("nan"),
                                              FieldErrorModel.stated(sigma, skin.n_nodes)))
    scans = []
    scan_step = prepared_estimator(skin)
    for k in range(args.scans):
        log(f"scan {k + 1} of {args.scans}")
        config = ScannerConfig(n_points=POINTS[args.resolution], noise_mm=0.03, marker_noise_mm=0.03, n_holes=3)
        scan = synthesize_scan(skin, members.displacement[args.fields + k], config, seed=args.seed + k)
        scans.append(field_from_scan(skin, scan.points, markers_mm=scan.markers,
                                     markers_nominal_mm=scan.markers_nominal, estimator=scan_step,
                                     marker_std_mm=0.03)[0])
    record: dict = {"date": time.strftime("%Y-%m-%d"), "nodes": skin.n_nodes, "pad_springs": int(reduced.k.size),
                    "args": vars(args), "cases": {}}
    for method in ("contact", "pca"):
        for kind, fields in (("noise field", noise_fields), ("scan", scans)):
            if fields:
                log(f"timing {method} on {len(fields)} {kind}s, coarsen {', '.join(map(str, strides))}")
                for stride, row in timed(bases, fields, method, args.repeat, strides).items():
                    record["cases"][f"{method}, {kind}, {stride}"] = row
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1, default=str))
    print(f"{skin.n_nodes} skin nodes, {reduced.k.size} pad springs; median CPU ms per estimate")
    print(f"{'case (method, field, coarsen)':<30} {'whole':>8} " + " ".join(f"{name:>8}" for name in PHASES))
    for case, row in record["cases"].items():
        print(f"{case:<30} {row['whole']:>8.1f} " + " ".join(f"{row[name]:>8.1f}" for name in PHASES))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
