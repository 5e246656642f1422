"""Closing the loop on missing effects that are not a candidate column (issue 14): one row per kind and noise level.

    scripts/with-env python benchmarks/bench_close_loop.py [--resolution default] [--seeds 5] [--noise 0.005 0.02]
                                                           [--calculix]

Truths (declared state TRUTH plus one physical change the candidates do not contain, each made by the FE model
through its own solver, never by the candidate code; Gaussian noise on the normal displacement):
  oblique      hinge_R moved x 0.5, z 0.3 mm (between two candidate directions)
  oblique_xy   hinge_R moved y 0.4, z 0.3 mm (an in-plane direction the skin confuses with x)
  patch_shift  hinge_R.z 0.5 mm applied at the hinge patch shifted 30 mm along -X (a model factorised anew)
  stiff_region a 10 % stiffer inner-panel region, radius 250 mm at (600, -300) mm
  gas_10deg    gas_spring_R pushing 10 deg off its axis, in its X-Z plane
  gas_10deg_y  the same, turned 10 deg out of that plane (towards +Y)
  calculix     (--calculix) CalculiX S8R load case and unit responses, pads lifted (LOCK_R +0.5, buffers -1 mm)
  none         no undeclared effect

For each seed the trace decides (core.loop.close_loop.trace_effect); "after" is the estimate with the named
candidates appended to the reduced model (what the rebuilt bases give the contact estimator) when they are found,
and the estimate before otherwise (a partial or unexplained outcome adds nothing). Prints a table (outcome counts,
the most frequent named set, residual RMS before / with the named candidates, worst declared error before / after,
medians over the seeds) and writes benchmarks/out/bench_close_loop.json.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import logging
import pathlib
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out" / "bench_close_loop.json"  # suffixed with the resolution
TRUTH = {"HINGE_X": 0.3, "HINGE_Y": -0.4, "LOCK_L": 0.6, "LOCK_R": -0.5, "BUFFER_L": 0.4, "BUFFER_R": -0.3}
logger = logging.getLogger("bench_close_loop")


def with_boundary(model, name: str, **changes):
    return dataclasses.replace(model, boundaries=tuple(
        dataclasses.replace(b, **changes) if b.name == name else b for b in model.boundaries))


def member(reduced, setting: dict[str, float]) -> np.ndarray:
    from hood_decomp.core.fe.ensemble import solve_members

    return solve_members(reduced, np.array([[setting.get(n, 0.0) for n in reduced.names]])).normal_displacement[0]


def truths(model, solver, calculix: bool) -> dict[str, tuple[np.ndarray, dict[str, float]]]:
    """kind -> (exact normal displacement (N,) mm, the declared truth of that part)."""
    from hood_decomp.core.fe.ensemble import simulate_setting
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model

    out = {"none": (simulate_setting(solver, TRUTH).normal_displacement, TRUTH)}
    out["oblique"] = (simulate_setting(solver, {**TRUTH, "hinge_R.x": 0.5, "hinge_R.z": 0.3}).normal_displacement,
                      TRUTH)
    out["oblique_xy"] = (simulate_setting(solver, {**TRUTH, "hinge_R.y": 0.4, "hinge_R.z": 0.3}).normal_displacement,
                         TRUTH)
    patch = model.boundary("hinge_R").patch
    shifted = with_boundary(model, "hinge_R", patch=dataclasses.replace(
        patch, center=(patch.center[0] - 30.0, patch.center[1], patch.center[2])))
    out["patch_shift"] = (simulate_setting(build_solver(shifted), {**TRUTH, "hinge_R.z": 0.5}).normal_displacement,
                          TRUTH)
    centres = model.nodes[model.cells].mean(axis=1)
    region = (model.cell_part == model.part_index("inner_panel")) & (
        np.hypot(centres[:, 0] - 600.0, centres[:, 1] + 300.0) < 250.0)
    out["stiff_region"] = (member(reduce_model(build_solver(model, stiffness_factor=np.where(region, 1.1, 1.0))),
                                  TRUTH), TRUTH)
    axis = np.asarray(model.boundary("gas_spring_R").axis)
    turn = np.radians(10.0)
    for kind, normal in (("gas_10deg", np.array([-axis[2], 0.0, axis[0]])), ("gas_10deg_y", np.array([0.0, 1.0, 0.0]))):
        rotated = np.cos(turn) * axis + np.sin(turn) * normal
        turned = with_boundary(model, "gas_spring_R", axis=tuple(float(v) for v in rotated))
        out[kind] = (member(reduce_model(build_solver(turned)), TRUTH), TRUTH)
    if calculix:
        from hood_decomp.core.fe.calculix import load_cases, run_cases

        setting = {**TRUTH, "LOCK_R": 0.5, "BUFFER_L": -1.0, "BUFFER_R": -1.0}
        cases, constrained = load_cases(model, pad_lattice=1)
        columns = run_cases(model, [c for c in cases if not c.name.startswith("pad_")], constrained)
        skin = model.skin_nodes
        displacement = columns["load"][skin] + sum(setting[p.label] * columns[f"unit_{p.label}"][skin]
                                                   for p in model.bilateral)
        out["calculix"] = (np.einsum("na,na->n", displacement, skin_surface(model).normals), setting)
    return out


def declared_worst(estimate, truth: dict[str, float]) -> float:
    """Largest |error| (mm) over the declared parameters the estimate does not report lifted."""
    return max(abs(float(v) - truth[n]) for n, v, lifted in zip(estimate.names, estimate.values, estimate.lifted,
                                                                strict=True) if n in truth and not lifted)


def run(resolution: str, seeds: int, noises: list[float], calculix: bool) -> dict:
    from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble
    from hood_decomp.core.fe.hood_preset import build_hood
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.loop.candidates import candidate_fields, enumerate_candidates
    from hood_decomp.core.loop.close_loop import _analyse, trace_effect
    from hood_decomp.core.method.bases import build_bases, estimate_field
    from hood_decomp.core.types import DisplacementField

    start = time.perf_counter()
    model = build_hood(resolution)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    commanded, rank = factorial_plan(model.lower, model.upper)
    bases = build_bases(simulate_ensemble(reduced, commanded, rank, model.lower, model.upper), skin_surface(model),
                        reduced)
    candidates = candidate_fields(solver, enumerate_candidates(model))
    fields = truths(model, solver, calculix)
    logger.info("model, bases, candidates and %d truths in %.0f s", len(fields), time.perf_counter() - start)
    rows = []
    for kind, (exact, truth) in fields.items():
        for sigma in noises:
            runs = []
            for seed in range(seeds):
                noise = np.random.default_rng(1000 * seed + 7).normal(0.0, sigma, exact.shape)
                field = DisplacementField(model.model_id, exact + noise, 1.0, sigma)
                before = estimate_field(bases, field)
                analyses, p_value, within = _analyse(bases, [before], [sigma], 0.01)
                trace = trace_effect(bases.reduced_model, bases.pca.lower_, bases.pca.upper_, [field], candidates,
                                     [before], [sigma])
                outcome = "within_model" if within else trace.outcome
                named = trace.named_estimates[0] if trace.named else before
                after = named if outcome == "found" else before
                runs.append({
                    "seed": seed, "outcome": outcome, "named": list(trace.named) if not within else [],
                    "p_value_before": p_value,
                    "rms_before_mm": analyses[0].rms_mm,
                    "rms_with_named_mm": float(np.sqrt(np.nanmean(named.residual**2))),
                    "worst_declared_before_mm": declared_worst(before, truth),
                    "worst_declared_after_mm": declared_worst(after, truth),
                    "best_explained": trace.best.explained,
                    "named_values": [float(v) for v in np.ravel(trace.pairs[0].values)] if len(trace.named) == 2
                    else [float(v) for v in trace.best.values] if trace.named else [],
                })
            counts = collections.Counter(r["outcome"] for r in runs)
            names = collections.Counter("+".join(r["named"]) or "-" for r in runs)
            row = {"kind": kind, "noise_mm": sigma, "outcomes": dict(counts), "named": names.most_common(1)[0][0],
                   "runs": runs}
            for key in ("rms_before_mm", "rms_with_named_mm", "worst_declared_before_mm", "worst_declared_after_mm",
                        "best_explained"):
                row[key] = float(np.median([r[key] for r in runs]))
            row["declared_no_worse"] = sum(r["worst_declared_after_mm"] <= r["worst_declared_before_mm"] + 1e-12
                                           for r in runs)
            rows.append(row)
            logger.info("%s at %.3g mm: %s", kind, sigma, dict(counts))
    return {"date": time.strftime("%Y-%m-%d"), "resolution": resolution, "seeds": seeds, "rows": rows,
            "seconds": time.perf_counter() - start}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", default="default", choices=("coarse", "default", "paper"))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.005, 0.02])
    parser.add_argument("--calculix", action="store_true", help="add a CalculiX-made part (5 ccx jobs)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("hood_decomp").setLevel(logging.WARNING)
    result = run(args.resolution, args.seeds, args.noise, args.calculix)
    print(f"\nclose loop on non-candidate effects, {args.resolution} hood, {args.seeds} seeds (medians)")
    print(f"{'kind':<13} {'noise':>6} {'outcomes':<34} {'named':<24} {'rms bef':>8} {'rms w/':>8} {'expl':>5} "
          f"{'decl bef':>9} {'decl aft':>9} {'no worse':>8}")
    for row in result["rows"]:
        outcomes = ", ".join(f"{k} {v}" for k, v in sorted(row["outcomes"].items()))
        print(f"{row['kind']:<13} {row['noise_mm']:>6.3f} {outcomes:<34} {row['named']:<24} "
              f"{row['rms_before_mm']:>8.4f} {row['rms_with_named_mm']:>8.4f} {row['best_explained']:>5.2f} "
              f"{row['worst_declared_before_mm']:>9.4f} {row['worst_declared_after_mm']:>9.4f} "
              f"{row['declared_no_worse']:>4}/{len(row['runs'])}")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    out = OUT.with_name(f"bench_close_loop_{args.resolution}.json")
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
