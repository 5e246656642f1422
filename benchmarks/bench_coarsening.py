"""The paper's coarsening of the input field, prototyped (issue 15: estimation at paper scale under 5 ms).

The paper: "This step could be accelerated significantly by coarsening the input displacement field". Here the
contact-aware estimate of a scan is made on a stratified subset of the skin's nodes (cells of ``--stride`` x the node
spacing in the skin's principal plane, the node nearest each cell's centre), with the scan's reading taken out on the
full field first, the field's error model restricted (node std on the subset, correlation sums 1 + (g - 1) n/N: the
subset keeps n/N of each node's correlated neighbours; the bias correlation x n/N; the pose as it is), and the
reduced model's rows and the within-model test's modes on the subset. Not the product's estimator: a measurement of
what a product version would state and cost, against the full estimate on the same harness (i)-like scans (random
states over the declared ranges, point noise 0.01-0.05 mm, marker noise 0.02-0.05 mm stated, 0-8 holes, the scan
step with its error model): coverage of the 95 % interval and RMS z per parameter, the std ratio, the test's alarms
at 1 %, CPU ms per estimate. Bases as ``bench_estimate.py`` takes them (``--bases`` / ``--store``).

Prints a table, writes benchmarks/out/coarsening.json. From the repository root:
    OPENBLAS_NUM_THREADS=1 scripts/with-env python benchmarks/bench_coarsening.py --store DIR --strides 2 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_estimate import POINTS, log, read_bases  # noqa: E402

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.method.bases import estimate_field, node_field  # noqa: E402
from hood_decomp.core.method.contact_estimation import ContactEstimator  # noqa: E402
from hood_decomp.core.method.model_spread import factor_spread  # noqa: E402
from hood_decomp.core.method.residual import ResidualTest  # noqa: E402
from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator  # noqa: E402
from hood_decomp.core.types import DisplacementField, SkinSurface  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "coarsening.json"


def stratified_nodes(points: np.ndarray, stride: int) -> np.ndarray:
    """(n,) sorted node indices: per cell of ``stride`` x the mean node spacing in the principal plane of ``points``
    (N, 3) mm, the node nearest the cell's centre."""
    centred = points - points.mean(axis=0)
    plane = centred @ np.linalg.svd(centred, full_matrices=False)[2][:2].T
    spacing = np.sqrt(np.ptp(plane[:, 0]) * np.ptp(plane[:, 1]) / points.shape[0])
    cell = np.floor((plane - plane.min(axis=0)) / (stride * spacing)).astype(np.int64)
    distance = np.linalg.norm(plane - ((cell + 0.5) * stride * spacing + plane.min(axis=0)), axis=1)
    key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
    order = np.lexsort((distance, key))
    first = np.r_[True, key[order][1:] != key[order][:-1]]
    return np.sort(order[first])


def coarsened(bases, nodes: np.ndarray):
    """The estimate of a field on ``nodes`` (module docstring), as a function of the field."""
    skin, reduced = bases.skin, bases.reduced_model
    ratio = nodes.size / skin.n_nodes
    sub_skin = SkinSurface(np.asarray(skin.points)[nodes], np.asarray(skin.normals)[nodes], np.zeros((0, 3), np.int64),
                           skin.model_id)
    rows = {name: getattr(reduced, name)[nodes] for name in ("w0", "R", "G", "w0_3d", "R_3d", "G_3d")}
    sub = dataclasses.replace(reduced, **rows)
    estimator = ContactEstimator().fit(sub, bases.pca.lower_, bases.pca.upper_, ResidualTest().fit(sub_skin), None,
                                       factor_spread(sub, bases.calibration, bases.physics))

    def estimate(field: DisplacementField):
        full = node_field(bases, field)
        errors = full.errors
        errors = dataclasses.replace(errors, node_std=np.asarray(errors.node_std)[nodes],
                                     correlation=1.0 + (np.asarray(errors.correlation)[nodes] - 1.0) * ratio,
                                     bias_correlation=errors.bias_correlation * ratio)
        return estimator.estimate(DisplacementField(field.model_id, full.normal_displacement[nodes], field.coverage,
                                                    field.noise_rms, errors))
    return estimate


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=tuple(POINTS), default="paper")
    parser.add_argument("--bases", type=Path, default=None, help="a bases file (else the built-in hood)")
    parser.add_argument("--store", type=Path, default=None, help="keep the built bases in DIR/bases.h5 and reuse it")
    parser.add_argument("--strides", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--scans", type=int, default=60)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    bases = read_bases(args)
    skin, reduced = bases.skin, bases.reduced_model
    ways = {"full": lambda field: estimate_field(bases, field)}
    sizes = {"full": skin.n_nodes}
    for stride in args.strides:
        nodes = stratified_nodes(np.asarray(skin.points, float), stride)
        ways[f"stride {stride}"], sizes[f"stride {stride}"] = coarsened(bases, nodes), nodes.size
    scan_step = prepared_estimator(skin)
    rng = np.random.default_rng(args.seed)
    lo, hi = bases.pca.lower_, bases.pca.upper_
    n_b = reduced.n_bilateral
    rows: dict[str, list[dict]] = {way: [] for way in ways}
    for k in range(args.scans):
        member = solve_members(reduced, rng.uniform(lo, hi)[None])
        marker = rng.uniform(0.02, 0.05)
        config = ScannerConfig(n_points=POINTS[args.resolution], noise_mm=rng.uniform(0.01, 0.05),
                               marker_noise_mm=marker, n_holes=int(rng.integers(0, 9)))
        scan = synthesize_scan(skin, member.displacement[0], config, seed=int(rng.integers(1 << 30)))
        field = field_from_scan(skin, scan.points, markers_mm=scan.markers, markers_nominal_mm=scan.markers_nominal,
                                estimator=scan_step, marker_std_mm=marker)[0]
        lifted = np.r_[np.zeros(n_b, bool), member.contact_fraction[0] == 0.0]
        for way, estimate in ways.items():
            estimate(field)  # warm
            start = time.process_time()
            result = estimate(field)
            cpu = 1e3 * (time.process_time() - start)
            z = np.where(result.lifted == lifted, (result.values - member.effective[0]) / result.std, np.nan)
            rows[way].append({"z": z.tolist(), "std": result.std.tolist(), "p": result.check.p_value, "cpu_ms": cpu})
        if (k + 1) % 10 == 0:
            log(f"scan {k + 1} of {args.scans}")
    full_std = np.array([row["std"] for row in rows["full"]])
    record: dict = {"date": time.strftime("%Y-%m-%d"), "names": list(bases.names), "args": vars(args), "ways": {}}
    for way, judged in rows.items():
        z = np.array([row["z"] for row in judged])
        record["ways"][way] = {
            "nodes": sizes[way],
            "std_ratio_median": np.nanmedian(np.array([row["std"] for row in judged]) / full_std, axis=0).tolist(),
            "inside_95": np.nanmean(np.abs(z) < 1.96, axis=0).tolist(),
            "rms_z": np.sqrt(np.nanmean(z**2, axis=0)).tolist(),
            "alarms": int(sum(row["p"] < 0.01 for row in judged)),
            "cpu_ms_median": float(np.median([row["cpu_ms"] for row in judged])), "rows": judged}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1, default=str))
    print(f"{args.scans} scans; per parameter {', '.join(bases.names)}")
    print(f"{'way':<10} {'nodes':>8} {'std/full':>22} {'inside 95 %':>30} {'alarms':>7} {'CPU ms':>7}")
    for way, row in record["ways"].items():
        ratio = " ".join(f"{v:.2f}" for v in row["std_ratio_median"])
        inside = " ".join(f"{100 * v:.0f}" for v in row["inside_95"])
        print(f"{way:<10} {row['nodes']:>8} {ratio:>22} {inside:>30} {row['alarms']:>7} {row['cpu_ms_median']:>7.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
