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

What the allowance states, per scan (issue 15 run 20): the bias' level per node and its smooth projection per
coefficient (mm^2; ``bias_variance_floor`` x ``bias_correlation`` is the stored one) for each of the stored 24 states,
each other state's truth and prediction, and per smooth mode; and along the parameters' gains: the estimate of a
noise-free scan (values of the noise-free field, error model of a 0.02 mm scan of the same state, markers 0.03 mm
stated) against the truth, beside the std the bias allowance adds to that scan's estimate (sqrt(std^2 - std^2 with
the allowance 1e-9 times as large)), RMS over the states.

Prints tables and writes benchmarks/out/scan_bias_<resolution>.json. Run from the repository root (paper: about
15 GB, under the memory lock):
    scripts/with-env nice python benchmarks/bench_scan_bias.py [--resolution coarse|default|paper] [--states N]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.loop.scan_skin import prepared_scan_skin, scan_bias, state_bias  # noqa: E402
from hood_decomp.core.method.bases import estimate_field  # noqa: E402
from hood_decomp.core.method.residual import bias_correlation_of, bias_split, smooth_modes  # noqa: E402
from hood_decomp.core.method.surface_reading import SurfaceGradient, slide  # noqa: E402
from hood_decomp.core.scan.scan_field import ScanFieldEstimator, field_from_scan, smoothing_bias_correlation  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402
from tests.conftest import _hood_case  # noqa: E402

#: scan points per resolution, as harness (i) (bench_uncertainty.POINTS)
POINTS = {"coarse": 120_000, "default": 500_000, "paper": 2_000_000}


def smooth_and_level(bias: np.ndarray, design: np.ndarray, errors, modes: np.ndarray) -> tuple[float, float]:
    """(smooth projection per coefficient, level per node) mm^2 of the biases (N, k) as the test splits them: the
    allowance's two factors' product and its floor (bias_split)."""
    correlation, level = bias_split(bias, design, errors, modes)
    return correlation * level, level


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=tuple(POINTS), default="coarse")
    parser.add_argument("--states", type=int, default=8)
    parser.add_argument("--points", type=int, default=None,
                        help="scan points (500,000 default, 120,000 coarse, 2,000,000 paper: bench_uncertainty's)")
    parser.add_argument("--seed", type=int, default=99)
    args = parser.parse_args()
    points = args.points or POINTS[args.resolution]
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
    noisy = ScannerConfig(n_points=points, noise_mm=0.02, marker_noise_mm=0.03, n_holes=0)
    allowance = float(arrays["bias_correlation"][0] * arrays["bias_variance_floor"][0])
    stored_biases, stored_errors = scan_bias(smoother, bases)  # the 24 states the allowance is measured on
    stored_split = [smooth_and_level(b[:, None], design, stored_errors, modes) for b in stored_biases.T]
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
        # along the gains: the noise-free scan's values with the error model of a 0.02 mm scan of the same state
        drawn = synthesize_scan(skin, moved, noisy, 1000 + k)
        scanned = field_from_scan(skin, drawn.points, markers_mm=drawn.markers,
                                  markers_nominal_mm=drawn.markers_nominal, estimator=smoother, marker_std_mm=0.03)[0]
        free = dataclasses.replace(scanned, normal_displacement=np.where(
            np.isfinite(scanned.normal_displacement), field.normal_displacement, np.nan))
        errors = scanned.errors
        off = dataclasses.replace(errors, bias_correlation=1e-9 * errors.bias_correlation)
        n_b = len(bases.names) - member.contact_fraction.shape[1]
        estimate = estimate_field(bases, free)
        right = estimate.lifted == np.r_[np.zeros(n_b, bool), member.contact_fraction[0] == 0.0]  # contact state
        std_on = estimate_field(bases, scanned).std
        std_off = estimate_field(bases, dataclasses.replace(scanned, error_model=off)).std
        truth_c2, truth_level = smooth_and_level(actual[:, None], design, field.error_model, modes)
        predicted_c2, predicted_level = smooth_and_level(predicted, design, predicted_errors, modes)
        biases.append(actual)
        slid_in.append(with_slide)
        rows.append({"state": k, "with_slide_rms_mm": float(np.sqrt(np.nanmean(with_slide**2))),
                     "actual_rms_mm": float(np.sqrt(np.nanmean(actual**2))),
                     "predicted_rms_mm": float(np.sqrt(np.nanmean(predicted**2))),
                     "node_correlation": float(np.corrcoef(actual[seen], predicted[seen, 0])[0, 1]),
                     "truth": bias_correlation_of(actual[:, None], design, field.error_model, modes),
                     "truth_with_slide": bias_correlation_of(with_slide[:, None], design, field.error_model, modes),
                     "predicted": bias_correlation_of(predicted, design, predicted_errors, modes),
                     "truth_smooth_mm2": truth_c2, "truth_level_mm2": truth_level,
                     "predicted_smooth_mm2": predicted_c2, "predicted_level_mm2": predicted_level,
                     "bias_error_mm": [float(v) if ok else None for v, ok in zip(
                         estimate.values - member.effective[0], right, strict=True)],
                     "allowance_std_mm": [float(v) for v in np.sqrt(np.clip(std_on**2 - std_off**2, 0.0, None))]})
    pooled = bias_correlation_of(np.column_stack(biases), design, field.error_model, modes)
    pooled_with_slide = bias_correlation_of(np.column_stack(slid_in), design, field.error_model, modes)
    smooth = np.array([row["truth_smooth_mm2"] for row in rows])
    stored_smooth = np.array([c2 for c2, _ in stored_split])
    error = np.array([[np.nan if v is None else v for v in row["bias_error_mm"]] for row in rows])
    added = np.array([row["allowance_std_mm"] for row in rows])
    gains = {name: {"bias_error_rms_mm": float(np.sqrt(np.nanmean(error[:, i] ** 2))),
                    "allowance_std_rms_mm": float(np.sqrt(np.mean(added[:, i] ** 2)))}
             for i, name in enumerate(bases.names)}
    result = {"date": time.strftime("%Y-%m-%d"), "args": vars(args), "stored": stored,
              "allowance_mm2": allowance, "floor_mm2": float(arrays["bias_variance_floor"][0]),
              "stored_states_smooth_mm2": stored_smooth.tolist(),
              "stored_states_level_mm2": [level for _, level in stored_split],
              "truth_smooth_pooled_mm2": float(np.mean(smooth)),
              "truth_level_pooled_mm2": float(np.mean([row["truth_level_mm2"] for row in rows])),
              "gains": gains,
              "area_fallback": smoothing_bias_correlation(skin), "truth_pooled": pooled,
              "truth_pooled_with_slide": pooled_with_slide, "measure_cpu_s": cost,
              "floor_rms_mm": float(np.sqrt(np.nanmean(floor.normal_displacement**2))), "states": rows}
    out = ROOT / "benchmarks" / "out" / f"scan_bias_{args.resolution}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"{'state':>5} {'RMS, slide in':>13} {'RMS scan':>9} {'RMS pred':>9} {'corr':>5} {'truth':>8} "
          f"{'pred':>8} {'truth, slide in':>15} {'smooth truth':>12} {'smooth pred':>11} {'level truth':>11}")
    for row in rows:
        print(f"{row['state']:>5} {row['with_slide_rms_mm']:>13.4f} {row['actual_rms_mm']:>9.4f} "
              f"{row['predicted_rms_mm']:>9.4f} {row['node_correlation']:>5.2f} {row['truth']:>8.1f} "
              f"{row['predicted']:>8.1f} {row['truth_with_slide']:>15.1f} {row['truth_smooth_mm2']:>12.2e} "
              f"{row['predicted_smooth_mm2']:>11.2e} {row['truth_level_mm2']:>11.2e}")
    print(f"smooth projection per coefficient, mm^2: allowance {allowance:.3g} (stored 24 states: "
          f"{np.min(stored_smooth):.2g}-{np.max(stored_smooth):.2g}, median {np.median(stored_smooth):.2g}); "
          f"{args.states} other states' truth {np.min(smooth):.2g}-{np.max(smooth):.2g}, mean {np.mean(smooth):.3g} "
          f"({np.mean(smooth) / allowance:.2f} x); level per node: floor {result['floor_mm2']:.3g}, truth "
          f"{result['truth_level_pooled_mm2']:.3g}")
    print(f"{'parameter':>10} {'bias-only error RMS (mm)':>25} {'std the allowance adds (mm)':>28} {'ratio':>6}")
    for name, row in gains.items():
        print(f"{name:>10} {row['bias_error_rms_mm']:>25.2e} {row['allowance_std_rms_mm']:>28.2e} "
              f"{row['bias_error_rms_mm'] / max(row['allowance_std_rms_mm'], 1e-300):>6.2f}")
    print(f"stored {stored:.1f} nodes (area fallback {result['area_fallback']:.1f}), truth pooled over "
          f"{args.states} states {pooled:.1f} (with the slide left in {pooled_with_slide:.1f}); measuring took "
          f"{cost:.2f} s CPU; undeformed part's field {result['floor_rms_mm']:.5f} mm RMS")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
