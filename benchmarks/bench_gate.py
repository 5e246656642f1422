"""Why the safety gate stays closed on harness (i) scans, and whether any estimator could open it (issue 15).

The gate (core/method/correction.py, ``CorrectionPolicy().max_std_mm`` 0.0045 mm: 4.5 std of it is the 0.02 mm an
applied correction may be wrong by) opens only when every touching boundary's total uncertainty sqrt(std^2 +
model_std^2) is below max_std. Per scan of harness (i) (bench_uncertainty's set-up: random states in the declared
ranges solved by the bases' own FE model, the synthetic scanner at ``--noise`` mm point noise, 0-8 holes, 8 fixture
markers with 0.02-0.05 mm centre noise, the scanner's marker noise stated), this records

- the estimate's std per boundary, the same with the field's registration term removed (pose covariance zeroed:
  what is left is node noise, smoothing bias and the spread between contact states), the model's physical factors'
  std (model_spread) and what shut the gate;
- a Cramer-Rao bound for the same data: the Fisher information of the boundaries on the seen nodes, J = X^T (D +
  U U^T)^-1 X, X (N, P) the FE model's own sensitivities at the true state (central differences, touching
  boundaries only), D = diag(node variance x correlation sum) of the field's error model (node noise only: no
  smoothing bias, no model error, so the bound is optimistic), U (N, 6) the registration's rigid-body modes from the
  stated marker noise. No unbiased estimator from this field and these markers has a smaller std; the same with
  the marker noise scaled to ``--marker-grid`` mm, and without any registration error (U = 0); "_bias": D with the
  smoothing bias the estimate itself states (its residual level split by split_level: the node covariance the
  stated std assumes, without the registration).

Prints a table and writes benchmarks/out/gate.json (rewritten as it goes). Run from the repository root:
    scripts/with-env nice python benchmarks/bench_gate.py [--resolution R] [--scans N] [--noise MM]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_uncertainty import closed_by, start_run  # noqa: E402

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.method.bases import estimate_field  # noqa: E402
from hood_decomp.core.method.correction import CorrectionPolicy, plan_correction  # noqa: E402
from hood_decomp.core.method.residual import node_variance, split_level  # noqa: E402
from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator  # noqa: E402
from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "gate.json"
MARKER_GRID_MM = (0.002, 0.005, 0.01, 0.02)
STEP_MM = 0.002  # central-difference step of the sensitivities (the contact state does not change over it)


def log(line: str) -> None:
    print(f"[bench_gate {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def sensitivities(reduced, state: np.ndarray) -> np.ndarray:
    """(N, P) d(normal displacement) / d(state) by central differences of the FE model at ``state``."""
    p = state.size
    steps = np.repeat(state[None], 2 * p, axis=0)
    steps[np.arange(0, 2 * p, 2), np.arange(p)] += STEP_MM
    steps[np.arange(1, 2 * p, 2), np.arange(p)] -= STEP_MM
    w = solve_members(reduced, steps).normal_displacement
    return ((w[0::2] - w[1::2]) / (2 * STEP_MM)).T


def cramer_rao(x: np.ndarray, variance: np.ndarray, modes: np.ndarray | None) -> np.ndarray:
    """(P,) sqrt(diag(J^-1)), J = X^T (D + U U^T)^-1 X by Woodbury; x (n, P), variance (n,), modes (n, k) or None."""
    wx = x / variance[:, None]
    information = x.T @ wx
    if modes is not None:
        wu = modes / variance[:, None]
        cross = x.T @ wu
        information -= cross @ np.linalg.solve(np.eye(modes.shape[1]) + modes.T @ wu, cross.T)
    return np.sqrt(np.diag(np.linalg.inv(information)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=("default", "coarse"), default="coarse")
    parser.add_argument("--scans", type=int, default=200)
    parser.add_argument("--noise", type=float, default=0.02, help="point noise, mm")
    parser.add_argument("--points", type=int, default=None,
                        help="scan points on the skin (default: 500,000 at default resolution, 120,000 at coarse)")
    parser.add_argument("--marker-grid", type=float, nargs="+", default=MARKER_GRID_MM,
                        help="marker noises (mm) the bound is also evaluated at")
    parser.add_argument("--marker-noise", type=float, nargs=2, default=(0.02, 0.05), metavar=("LOW", "HIGH"),
                        help="range of the scans' marker-centre noise, mm (harness (i): 0.02-0.05)")
    parser.add_argument("--seed", type=int, default=25)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    case, rng, record, save = start_run(args, log)
    bases, reduced, skin = case.bases, case.reduced, case.skin
    names = list(bases.names)
    n_bilateral = bases.pca.n_bilateral_
    max_std = CorrectionPolicy().max_std_mm
    est = prepared_estimator(skin)
    rows: list[dict] = []
    start = time.time()
    for k in range(args.scans):
        state = rng.uniform(bases.pca.lower_, bases.pca.upper_)
        marker_noise, holes, seed = rng.uniform(*args.marker_noise), int(rng.integers(0, 9)), int(rng.integers(1 << 30))
        member = solve_members(reduced, state[None])
        config = ScannerConfig(n_points=args.points, noise_mm=args.noise, marker_noise_mm=marker_noise,
                               n_holes=holes)
        scan = synthesize_scan(skin, member.displacement[0], config, seed=seed)
        field, registration = field_from_scan(skin, scan.points, markers_mm=scan.markers,
                                              markers_nominal_mm=scan.markers_nominal, estimator=est,
                                              marker_std_mm=marker_noise)
        estimate = estimate_field(bases, field)
        correction = plan_correction(estimate)
        no_pose = estimate_field(bases, dataclasses.replace(field, error_model=dataclasses.replace(
            field.errors, pose_covariance=np.zeros((6, 6)))))
        model_std = np.zeros(len(names)) if estimate.model_effects is None else estimate.model_std
        # the bound, over the boundaries that touch in the truth (a lifted pad moves nothing: no information)
        touching = np.ones(len(names), bool)
        touching[n_bilateral:] = member.contact_fraction[0] > 0.0
        valid = np.isfinite(field.normal_displacement)
        x = sensitivities(reduced, state)[valid][:, touching]
        node_var, correlation = node_variance(field.errors, skin.n_nodes)
        variance = (node_var * correlation)[valid]
        # the node covariance the estimate itself states: the residual's level split into noise and smoothing bias
        scale, bias = split_level(estimate.check.noise_scale, field.errors, float(node_var[valid].mean()))
        with_bias = scale * variance + bias
        used = registration.marker_noise.used_mm
        modes = field.errors.registration_modes(skin.points, skin.normals)[valid]
        bounds = {"stated": cramer_rao(x, variance, modes), "none": cramer_rao(x, variance, None),
                  "stated_bias": cramer_rao(x, with_bias, modes), "none_bias": cramer_rao(x, with_bias, None),
                  **{f"{s:g}": cramer_rao(x, variance, modes * (s / used)) for s in args.marker_grid},
                  **{f"{s:g}_bias": cramer_rao(x, with_bias, modes * (s / used)) for s in args.marker_grid}}

        def full(values: np.ndarray, touching: np.ndarray = touching) -> list[float | None]:
            out = np.full(len(names), np.nan)
            out[touching] = values
            return [None if not np.isfinite(v) else float(v) for v in out]

        rows.append({
            "scan": k, "marker_noise_mm": marker_noise, "holes": holes, "coverage": field.coverage,
            "touching": touching.tolist(), "lifted": np.asarray(estimate.lifted).tolist(),
            "std_mm": estimate.std.tolist(), "std_no_pose_mm": no_pose.std.tolist(), "model_std_mm": model_std.tolist(),
            "within": bool(estimate.within_model), "safe": bool(correction.safe_to_apply),
            "reasons": closed_by(correction), "applicable": [n for n, a in zip(names, correction.applicable,
                                                                             strict=True) if a],
            "error_mm": (estimate.values - member.effective[0]).tolist(),
            "crb_mm": {key: full(value) for key, value in bounds.items()}})
        if (k + 1) % 10 == 0 or k + 1 == args.scans:
            record["summary"] = summarise(rows, names, max_std, args.marker_grid)
            record["rows"] = rows
            save()
            log(f"scan {k + 1}: {(time.time() - start) / (k + 1):.1f} s per scan, gate open "
                f"{record['summary']['gate_open']:.3f}, possible (bound, no model std) "
                f"{record['summary']['possible']['stated']:.3f}")
    print_table(record["summary"], names)
    return 0


def summarise(rows: list[dict], names: list[str], max_std: float, grid) -> dict:
    """Per boundary: medians of std, std without the registration, their difference in quadrature, model std and the
    bounds; how often its own total is below max_std; per marker noise, in how many scans the bound (alone, and with
    the model std) lets every touching boundary under max_std: the most any estimator could open the gate."""
    def column(key: str) -> np.ndarray:
        return np.array([[np.nan if v is None else v for v in r[key]] for r in rows], float)

    std, no_pose, model, error = column("std_mm"), column("std_no_pose_mm"), column("model_std_mm"), column("error_mm")
    lifted = np.array([r["lifted"] for r in rows], bool)
    crb = {key: np.array([[np.nan if v is None else v for v in r["crb_mm"][key]] for r in rows], float)
           for key in rows[0]["crb_mm"]}
    per: dict = {}
    for i, name in enumerate(names):
        seen = ~lifted[:, i]
        total = np.hypot(std[:, i], model[:, i])
        per[name] = {
            "std_median_mm": float(np.median(std[seen, i])),
            "std_no_pose_median_mm": float(np.median(no_pose[seen, i])),
            "registration_share_median_mm": float(np.median(np.sqrt(np.clip(
                std[seen, i] ** 2 - no_pose[seen, i] ** 2, 0.0, None)))),
            "model_std_median_mm": float(np.median(model[seen, i])),
            "std_below_max": float(np.mean(std[seen, i] <= max_std)),
            "total_below_max": float(np.mean(total[seen] <= max_std)),
            "applicable": float(np.mean([name in r["applicable"] for r in rows])),
            # the std's honesty where it is used: error / std (contact state of the estimate, not checked here)
            "rms_z": float(np.sqrt(np.mean((error[seen, i] / std[seen, i]) ** 2))),
            "inside_95": float(np.mean(np.abs(error[seen, i] / std[seen, i]) <= 1.959964)),
            "rms_error_mm": float(np.sqrt(np.mean(error[seen, i] ** 2))),
            **{f"crb_{key}_median_mm": float(np.nanmedian(value[:, i])) if np.isfinite(value[:, i]).any() else None
               for key, value in crb.items()}}
    possible, possible_model = {}, {}
    for key, value in crb.items():
        touching = np.isfinite(value)
        ok = np.where(touching, value <= max_std, True).all(axis=1)
        ok_model = np.where(touching, np.hypot(value, model) <= max_std, True).all(axis=1)
        possible[key], possible_model[key] = float(np.mean(ok)), float(np.mean(ok_model))
    kinds = [kind for r in rows for kind in r["reasons"]]
    return {"n": len(rows), "max_std_mm": max_std, "gate_open": float(np.mean([r["safe"] for r in rows])),
            "false_alarms": float(np.mean([not r["within"] for r in rows])),
            "gate_closed_by": {kind: kinds.count(kind) for kind in sorted(set(kinds))},
            "max_abs_error_mm": float(np.nanmax(np.abs(np.where(lifted, np.nan, error)))),
            "per_boundary": per, "possible": possible, "possible_with_model_std": possible_model,
            "marker_grid_mm": list(grid)}


def print_table(summary: dict, names: list[str]) -> None:
    keys = ["std_median_mm", "std_no_pose_median_mm", "registration_share_median_mm", "model_std_median_mm",
            "crb_stated_median_mm", "crb_stated_bias_median_mm", "crb_none_bias_median_mm", "std_below_max",
            "total_below_max", "applicable", "rms_error_mm", "rms_z", "inside_95"]
    print(f"{'boundary':<10} " + " ".join(f"{k.replace('_median_mm', '').replace('_', ' '):>13}" for k in keys))
    for name in names:
        row = summary["per_boundary"][name]
        print(f"{name:<10} " + " ".join(f"{(row[k] if row[k] is not None else float('nan')):>13.4f}" for k in keys))
    print(f"gate open {summary['gate_open']:.3f} of {summary['n']}; closed by {summary['gate_closed_by']}")
    for key in summary["possible"]:
        print(f"bound at marker noise {key:>7}: every touching boundary <= {summary['max_std_mm']} mm in "
              f"{summary['possible'][key]:.3f} of scans ({summary['possible_with_model_std'][key]:.3f} with the "
              "model std)")


if __name__ == "__main__":
    raise SystemExit(main())
