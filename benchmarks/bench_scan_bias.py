"""The scan step's bias correlation a prepared skin stores, against noise-free synthetic scans of FE states (issue 15
run 10).

Measured (what the bases file stores, core/loop/scan_skin.py): 24 FE states through the scan step's own smoother,
split by the within-model test's arithmetic (core.method.residual.bias_correlation_of). Truth: ``--states`` other FE
states scanned noise-free by the synthetic scanner (Phong surface, ray-cast points, no pose error) through the public
field path (no outlier pass: on a noise-free cloud it drops the curvature's own residuals), field minus what a scan
reads of the FE state (its normal displacement less the slide u_t . grad u_n, core.method.surface_reading, which the
estimator takes out), split the same way, per state and pooled; beside it the field minus the normal displacement
(the slide left in). Also per state what the stored measurement makes of that state (core.loop.scan_skin.state_bias:
the scan step's field path on its surface samples) and the undeformed part's field (the nominal geometry's floor).

Prints a table and writes benchmarks/out/scan_bias_<resolution>.json. Run from the repository root:
    scripts/with-env nice python benchmarks/bench_scan_bias.py [--resolution coarse|default] [--states N]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.loop.scan_skin import prepared_scan_skin, state_bias  # noqa: E402
from hood_decomp.core.method.residual import bias_correlation_of, smooth_modes  # noqa: E402
from hood_decomp.core.method.surface_reading import SurfaceGradient, slide  # noqa: E402
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan, smoothing_bias_correlation  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402
from tests.conftest import _hood_case  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=("default", "coarse"), default="coarse")
    parser.add_argument("--states", type=int, default=8)
    parser.add_argument("--points", type=int, default=None, help="scan points (500,000 default, 120,000 coarse)")
    parser.add_argument("--seed", type=int, default=99)
    args = parser.parse_args()
    points = args.points or (500_000 if args.resolution == "default" else 120_000)
    with tempfile.TemporaryDirectory() as tmp:
        case = _hood_case(args.resolution, Path(tmp))
    bases, skin = case.bases, case.skin
    start = time.process_time()
    arrays = prepared_scan_skin(bases)
    cost = time.process_time() - start
    stored = float(arrays["bias_correlation"][0])
    smoother = ScanFieldEstimator().fit(skin, prepared=arrays)
    scanner = ScanFieldEstimator(outlier_sigma=1e9).fit(skin, prepared=arrays)
    modes, design = smooth_modes(skin.points, 2), bases.pca.components_.T
    gradient = SurfaceGradient.fit(skin)
    config = ScannerConfig(n_points=points, noise_mm=0.0, pose_error_deg=0.0, pose_error_mm=0.0, n_holes=0,
                           outlier_fraction=0.0, dropout_fraction=0.0)
    flat = synthesize_scan(skin, np.zeros((skin.n_nodes, 3)), config, 0)
    floor = field_from_scan(skin, flat.points, scanner_pose=flat.true_transform, estimator=scanner)[0]
    rng = np.random.default_rng(args.seed)
    rows, biases, slid_in = [], [], []
    for k in range(args.states):
        member = solve_members(case.reduced, rng.uniform(bases.pca.lower_, bases.pca.upper_)[None])
        normal, moved = member.normal_displacement[0], member.displacement[0]
        scan = synthesize_scan(skin, moved, config, k)
        field = field_from_scan(skin, scan.points, scanner_pose=scan.true_transform, estimator=scanner)[0]
        with_slide = field.normal_displacement - normal
        actual = with_slide + slide(gradient, normal, moved)
        predicted, predicted_errors = state_bias(smoother, gradient, moved)
        predicted = predicted[:, None]
        seen = np.isfinite(actual) & np.isfinite(predicted[:, 0])
        biases.append(actual)
        slid_in.append(with_slide)
        rows.append({"state": k, "with_slide_rms_mm": float(np.sqrt(np.nanmean(with_slide**2))),
                     "actual_rms_mm": float(np.sqrt(np.nanmean(actual**2))),
                     "predicted_rms_mm": float(np.sqrt(np.nanmean(predicted**2))),
                     "node_correlation": float(np.corrcoef(actual[seen], predicted[seen, 0])[0, 1]),
                     "truth": bias_correlation_of(actual[:, None], design, field.error_model, modes),
                     "truth_with_slide": bias_correlation_of(with_slide[:, None], design, field.error_model, modes),
                     "predicted": bias_correlation_of(predicted, design, predicted_errors, modes)})
    pooled = bias_correlation_of(np.column_stack(biases), design, field.error_model, modes)
    pooled_with_slide = bias_correlation_of(np.column_stack(slid_in), design, field.error_model, modes)
    result = {"date": time.strftime("%Y-%m-%d"), "args": vars(args), "stored": stored,
              "area_fallback": smoothing_bias_correlation(skin), "truth_pooled": pooled,
              "truth_pooled_with_slide": pooled_with_slide, "measure_cpu_s": cost,
              "floor_rms_mm": float(np.sqrt(np.nanmean(floor.normal_displacement**2))), "states": rows}
    out = ROOT / "benchmarks" / "out" / f"scan_bias_{args.resolution}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"{'state':>5} {'RMS, slide in':>13} {'RMS scan':>9} {'RMS pred':>9} {'corr':>5} {'truth':>8} "
          f"{'pred':>8} {'truth, slide in':>15}")
    for row in rows:
        print(f"{row['state']:>5} {row['with_slide_rms_mm']:>13.4f} {row['actual_rms_mm']:>9.4f} "
              f"{row['predicted_rms_mm']:>9.4f} {row['node_correlation']:>5.2f} {row['truth']:>8.1f} "
              f"{row['predicted']:>8.1f} {row['truth_with_slide']:>15.1f}")
    print(f"stored {stored:.1f} nodes (area fallback {result['area_fallback']:.1f}), truth pooled over "
          f"{args.states} states {pooled:.1f} (with the slide left in {pooled_with_slide:.1f}); measuring took "
          f"{cost:.2f} s CPU; undeformed part's field {result['floor_rms_mm']:.5f} mm RMS")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
