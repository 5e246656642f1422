"""The paper's coarsening of the input field on harness (i)-like scans (issue 15: estimation at paper scale under 5 ms).

The paper: "This step could be accelerated significantly by coarsening the input displacement field". The product's
coarsened estimate (``estimate_field(..., coarsen=STRIDE)``, core.method.coarsening: a stratified subset of the skin's
nodes, the scan's reading taken out on every node first, the field's error model restricted with its correlation sums
scaled to the kept nodes, the estimate carried back to every node) against the estimate on every node, on the same
harness (i)-like scans (random states over the declared ranges, point noise 0.01-0.05 mm, marker noise 0.02-0.05 mm
stated, 0-8 holes, the scan step with its error model): coverage of the 95 % interval and RMS z per parameter, the
std ratio and the actual error's RMS ratio to the full estimate's, the test's alarms at 1 %, CPU ms per estimate.
Bases as ``bench_estimate.py`` takes them (``--bases`` / ``--store``).

Prints a table, writes benchmarks/out/coarsening.json. From the repository root:
    OPENBLAS_NUM_THREADS=1 scripts/with-env python benchmarks/bench_coarsening.py --store DIR --strides 2 3
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_estimate import POINTS, log, read_bases  # noqa: E402

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.method.bases import estimate_field  # noqa: E402
from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "coarsening.json"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=tuple(POINTS), default="paper")
    parser.add_argument("--bases", type=Path, default=None, help="a bases file (else the built-in hood)")
    parser.add_argument("--store", type=Path, default=None, help="keep the built bases in DIR/bases.h5 and reuse it")
    parser.add_argument("--strides", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--method", choices=("contact", "pca"), default="contact")
    parser.add_argument("--scans", type=int, default=60)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    bases = read_bases(args)
    skin, reduced = bases.skin, bases.reduced_model
    strides = {"full": 1, **{f"stride {stride}": stride for stride in args.strides}}
    sizes = {way: bases.coarsened(stride).nodes.size if stride > 1 else skin.n_nodes for way, stride in strides.items()}
    scan_step = prepared_estimator(skin)
    rng = np.random.default_rng(args.seed)
    lo, hi = bases.pca.lower_, bases.pca.upper_
    n_b = reduced.n_bilateral
    rows: dict[str, list[dict]] = {way: [] for way in strides}
    for k in range(args.scans):
        member = solve_members(reduced, rng.uniform(lo, hi)[None])
        marker = rng.uniform(0.02, 0.05)
        config = ScannerConfig(n_points=POINTS[args.resolution], noise_mm=rng.uniform(0.01, 0.05),
                               marker_noise_mm=marker, n_holes=int(rng.integers(0, 9)))
        scan = synthesize_scan(skin, member.displacement[0], config, seed=int(rng.integers(1 << 30)))
        field = field_from_scan(skin, scan.points, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal,
                                estimator=scan_step, marker_std_mm=marker)[0]
        lifted = np.r_[np.zeros(n_b, bool), member.contact_fraction[0] == 0.0]
        for way, stride in strides.items():
            estimate_field(bases, field, args.method, coarsen=stride)  # warm
            start = time.process_time()
            result = estimate_field(bases, field, args.method, coarsen=stride)
            cpu = 1e3 * (time.process_time() - start)
            error = np.where(result.lifted == lifted, result.values - member.effective[0], np.nan)
            rows[way].append({"z": (error / result.std).tolist(), "error": error.tolist(), "std": result.std.tolist(),
                              "p": result.check.p_value, "cpu_ms": cpu})
        if (k + 1) % 10 == 0:
            log(f"scan {k + 1} of {args.scans}")
    full_std = np.array([row["std"] for row in rows["full"]])
    full_error = np.array([row["error"] for row in rows["full"]])
    record: dict = {"date": time.strftime("%Y-%m-%d"), "names": list(bases.names), "args": vars(args), "ways": {}}
    for way, judged in rows.items():
        z = np.array([row["z"] for row in judged])
        record["ways"][way] = {
            "nodes": sizes[way],
            "std_ratio_median": np.nanmedian(np.array([row["std"] for row in judged]) / full_std, axis=0).tolist(),
            "error_rms_ratio": np.sqrt(np.nanmean(np.array([row["error"] for row in judged]) ** 2, axis=0)
                                       / np.nanmean(full_error**2, axis=0)).tolist(),
            "inside_95": np.nanmean(np.abs(z) < 1.96, axis=0).tolist(),
            "rms_z": np.sqrt(np.nanmean(z**2, axis=0)).tolist(),
            "alarms": int(sum(row["p"] < 0.01 for row in judged)),
            "cpu_ms_median": float(np.median([row["cpu_ms"] for row in judged])), "rows": judged}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1, default=str))
    print(f"{args.scans} scans; per parameter {', '.join(bases.names)}")
    print(f"{'way':<10} {'nodes':>8} {'std/full':>30} {'error RMS/full':>30} {'inside 95 %':>24} {'alarms':>7} "
          f"{'CPU ms':>7}")
    for way, row in record["ways"].items():
        ratio = " ".join(f"{v:.2f}" for v in row["std_ratio_median"])
        error = " ".join(f"{v:.2f}" for v in row["error_rms_ratio"])
        inside = " ".join(f"{100 * v:.0f}" for v in row["inside_95"])
        print(f"{way:<10} {row['nodes']:>8} {ratio:>30} {error:>30} {inside:>24} {row['alarms']:>7} "
              f"{row['cpu_ms_median']:>7.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
