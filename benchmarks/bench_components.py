"""Benchmark: fitting all three displacement components against the normal one (issue 21, ``components="xyz"``).

Through the product's path (bases, ``estimate_field``) on one preset and resolution: ``--members`` fields per kind of
truth, each with one draw of white noise of ``--noise`` mm on every component (the normal values the normal part of
the same noisy vectors, no error model: a simulated field), estimated by both estimators with both component sets.

Kinds of truth (``--kinds``; the default ``own`` alone):

- ``own``: random states of the model (validation plan, seed 11), the bases' own reduced model's 3D member fields;
- ``ccx_nominal`` / ``ccx_family``: the same hood by CalculiX S8R shells
  (:class:`~hood_decomp.synthetic.standin.StandIn` on a cached npz of its responses, ``--ccx-cache``, never made
  here; by default the shared cache of the resolution, the default hood's without pad jobs: the embedded solver's
  pad responses there), nominal physics / a
  :class:`~hood_decomp.synthetic.standin.Family` drawn per field (E +-3 %, thickness +-5 %, pad stiffness +-30 %,
  preload +-50 %, gas force +-5 %);
- ``physics``: the bases' own embedded solver with perturbed physics (E +-3 %, thickness +-5 %, pad stiffness
  +-30 %, gas force +-5 %, all drawn per field: issue 15 harness (ii)'s ``physics_all``);
- ``mesh_finer`` (coarse bases only): the hood solved on the default mesh, its 3D displacement interpolated linearly
  onto the coarse skin nodes in the skin's grid coordinates.
``--other-models``: every kind. Other kinds' states: uniform in the bases' ranges (seed ``--seed``).

Per kind and run: the median estimate time (ms; the estimator prepared first, its time apart); per bilateral
parameter the RMS and largest error against the truth's state (mm), the median stated std, the RMS of error / std
and the coverage of the 95 % interval (+-1.96 std; for the contact-aware estimator also with the model's physical
factors, sqrt(std^2 + model_std^2)); the share of fields the within-model test rejects (alpha 0.01); "moved": fields
whose noise-free estimate (the truth field itself) is off the truth by more than 2 stated std in some bilateral
parameter (what the model's discrepancy does to the estimate, issue 15), and how many of them the test rejects; the
same beyond 2 total std (with the model's factors); the coverage of the fields the test passes.
``--with-physics``: the bases also carry the FE model's responses to sheet thickness and gas springs (as issue 15's
bench_discrepancy), so the contact-aware estimator's model std counts all its factors.

Usage: scripts/with-env python benchmarks/bench_components.py [--preset hood|hood-paper] [--resolution coarse]
       [--members 40] [--noise 0.01] [--kinds own ccx_nominal ... | --other-models] [--with-physics]
Prints a table and writes benchmarks/out/bench_components_<preset>_<resolution>[_<kinds>_noise<mm>[_physics]].json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from bench_partial_contact import bases_of

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # tests.core.method.test_truth_elsewhere's grid coordinates (mesh_finer)
OUT = ROOT / "benchmarks" / "out"
CACHE = Path("/work/scratch/cache")
KINDS = ("own", "ccx_nominal", "ccx_family", "physics", "mesh_finer")
PHYSICS = ("E", "thickness", "pad_stiffness", "gas_spring")
MOVED_STD = 2.0


def log(line: str) -> None:
    print(f"[bench_components {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def truths(kind: str, preset: str, resolution: str, bases, reduced, model, members: int, rng: np.random.Generator,
           ccx_cache: Path) -> tuple[np.ndarray, np.ndarray] | str:
    """(displacement (m, N, 3) mm on the bases' skin nodes, effective states (m, P) mm) of ``members`` fields of
    ``kind`` (``model``: the bases' PartModel, of ``preset`` at ``resolution``), or the reason it is not run."""
    from hood_decomp.core.fe.ensemble import solve_members, validation_plan
    from hood_decomp.synthetic.standin import (
        FAMILY_SPREAD,
        THICKNESS_SCALES,
        Family,
        StandIn,
        calculix_responses,
        embedded_responses,
        serial_responses,
    )

    lo, hi = bases.pca.lower_, bases.pca.upper_
    if kind == "own":
        block = solve_members(reduced, validation_plan(lo, hi, members, seed=11))
        return block.displacement, block.effective
    settings = rng.uniform(lo, hi, (members, lo.size))
    if kind == "mesh_finer":
        if resolution != "coarse":
            return "the finer mesh is the default hood's: only against coarse bases"
        from scipy.interpolate import LinearNDInterpolator

        from hood_decomp.core.fe.hood_preset import build_preset
        from hood_decomp.core.fe.model import skin_surface
        from hood_decomp.core.fe.solver import build_solver, reduce_model
        from tests.core.method.test_truth_elsewhere import _grid_coordinates

        fine = build_preset(preset, "default")
        block = solve_members(reduce_model(build_solver(fine)), settings)
        source, target = _grid_coordinates(skin_surface(fine).points), _grid_coordinates(bases.skin.points)
        moved = np.stack([LinearNDInterpolator(source, u)(target) for u in block.displacement])
        return moved, block.effective
    if kind == "physics":
        log("the embedded solver's responses at three thickness scales (perturbed physics)")
        standin = StandIn(model, embedded_responses(model))
        families = [Family(**{key: float(1.0 + rng.uniform(-FAMILY_SPREAD[key], FAMILY_SPREAD[key]))
                              for key in PHYSICS}) for _ in range(members)]
    else:
        if not ccx_cache.exists():
            return f"no CalculiX cache at {ccx_cache} (never run here)"
        with np.load(ccx_cache, allow_pickle=False) as data:
            # a cache of another model or of other scales would be made again by CalculiX (hours): refused here
            scales = tuple(data["scales"].tolist()) if "scales" in data.files else ()
            if str(data["model_id"]) != model.model_id or scales != THICKNESS_SCALES:
                return (f"{ccx_cache} holds model {data['model_id']} at thickness scales {scales}, not "
                        f"{model.model_id}'s at {THICKNESS_SCALES}")
        if resolution != "coarse":
            # the default hood's CalculiX jobs without pads (68 pad jobs of ~7.7 GB are out of reach)
            standin = StandIn(model, serial_responses(model, ccx_cache), embedded_pads=True)
        else:
            standin = StandIn(model, calculix_responses(model, cache=ccx_cache))
        families = [Family() if kind == "ccx_nominal" else Family.draw(rng) for _ in range(members)]
    blocks = [solve_members(standin.reduced(family), setting[None]) for family, setting in
              zip(families, settings, strict=True)]
    return np.concatenate([b.displacement for b in blocks]), np.concatenate([b.effective for b in blocks])


def judged(bases, kind_truths: tuple[np.ndarray, np.ndarray], noise: float, rng: np.random.Generator
           ) -> dict[str, dict]:
    """Every estimator and component set on the truths (displacement (m, N, 3), effective (m, P)), each field with
    one draw of ``noise`` mm white noise per component: per run the summary of :func:`summary`."""
    from hood_decomp.core.method.bases import estimate_field
    from hood_decomp.core.types import DisplacementField

    normals = bases.skin.normals
    n_b = bases.reduced_model.n_bilateral

    def field(vectors: np.ndarray) -> DisplacementField:
        return DisplacementField(bases.model_id, np.einsum("na,na->n", vectors, normals), 1.0, float("nan"),
                                 displacement=vectors)

    displacement, effective = kind_truths
    noisy = [field(u + rng.normal(0.0, noise, u.shape)) for u in displacement]
    clean = [field(u) for u in displacement]
    runs = {}
    for method in ("contact", "pca"):
        for components in ("normal", "xyz"):
            tic = time.perf_counter()
            bases.prepare_estimation(method, 0.2, 0.0, components)
            prepare = time.perf_counter() - tic
            rows = {"time": [], "error": [], "std": [], "model_std": [], "within": [], "shift": []}
            for noisy_field, clean_field, truth in zip(noisy, clean, effective, strict=True):
                tic = time.perf_counter()
                estimate = estimate_field(bases, noisy_field, method, components=components)
                rows["time"].append(time.perf_counter() - tic)
                rows["error"].append(estimate.values[:n_b] - truth[:n_b])
                rows["std"].append(estimate.std[:n_b])
                model_std = estimate.model_std
                rows["model_std"].append(np.zeros(n_b) if model_std is None else model_std[:n_b])
                rows["within"].append(estimate.within_model)
                # the discrepancy's own shift of the estimate: the truth field itself, estimated alike
                rows["shift"].append(estimate_field(bases, clean_field, method, components=components).values[:n_b]
                                     - truth[:n_b])
            runs[f"{method} {components}"] = summary(rows, bases.names[:n_b]) | {"prepare_s": prepare}
    return runs


def summary(rows: dict[str, list], names: tuple[str, ...]) -> dict[str, object]:
    """One run's numbers from per-field rows (error, std, model_std, shift (m, B) mm; within (m,); time (m,) s)."""
    error, std, model_std, shift = (np.array(rows[key]) for key in ("error", "std", "model_std", "shift"))
    within = np.array(rows["within"], dtype=bool)
    total = np.hypot(std, model_std)
    moved = np.any(np.abs(shift) > MOVED_STD * std, axis=1)
    moved_total = np.any(np.abs(shift) > MOVED_STD * total, axis=1)  # beyond the model's factors too

    def per(values: np.ndarray) -> dict[str, float]:
        return dict(zip(names, values.tolist(), strict=True))

    return {
        "estimate_ms_median": 1e3 * float(np.median(rows["time"])),
        "rms_error_mm": per(np.sqrt(np.mean(error ** 2, axis=0))),
        "max_error_mm": per(np.max(np.abs(error), axis=0)),
        "median_std_mm": per(np.median(std, axis=0)),
        "rms_z": per(np.sqrt(np.mean((error / std) ** 2, axis=0))),
        "coverage_95": per(np.mean(np.abs(error) <= 1.96 * std, axis=0)),
        # with the model's physical factors (contact-aware estimator; the same as coverage_95 where none are stated)
        "coverage_95_total": per(np.mean(np.abs(error) <= 1.96 * total, axis=0)),
        "rms_shift_z": per(np.sqrt(np.mean((shift / std) ** 2, axis=0))),
        "rms_shift_mm": per(np.sqrt(np.mean(shift ** 2, axis=0))),
        # the fields the test passes: what a user takes as the model's, and how often their interval holds
        "accepted_coverage_95_total": per(np.mean(np.abs(error[within]) <= 1.96 * total[within], axis=0)
                                          if within.any() else np.full(len(names), np.nan)),
        "rejected_share": float(np.mean(~within)),
        "moved": int(moved.sum()),
        "moved_rejected": int(np.sum(moved & ~within)),
        "unmoved_rejected": int(np.sum(~moved & ~within)),
        "moved_total": int(moved_total.sum()),
        "moved_total_rejected": int(np.sum(moved_total & ~within)),
        "fields": int(within.size),
    }


def run(preset: str, resolution: str, members: int, noise: float, kinds: tuple[str, ...], seed: int,
        ccx_cache: Path, with_physics: bool = False) -> dict[str, object]:
    from hood_decomp.core.fe.hood_preset import build_preset

    started = time.perf_counter()
    bases, reduced = bases_of(preset, resolution)
    built = time.perf_counter() - started
    model = build_preset(preset, resolution)
    if with_physics:
        import dataclasses

        from hood_decomp.core.fe.solver import build_solver, physical_responses, thermal_moves, thickness_sensitivities
        from hood_decomp.core.method.model_spread import PhysicalResponses

        log("the FE model's responses to gas springs and sheet thickness (the model's factors, model_spread)")
        physics = PhysicalResponses.from_solver(physical_responses(build_solver(model)),
                                                thickness_sensitivities(model, reduced), thermal_moves(model))
        bases = dataclasses.replace(bases, physics=physics)
    rng = np.random.default_rng(seed)
    noise_rng = np.random.default_rng(0)
    results: dict[str, object] = {}
    for kind in kinds:
        log(f"{kind}: {members} truths")
        made = truths(kind, preset, resolution, bases, reduced, model, members, rng, ccx_cache)
        if isinstance(made, str):
            log(f"{kind} not run: {made}")
            results[kind] = {"not_run": made}
            continue
        results[kind] = judged(bases, made, noise, noise_rng)
    return {"preset": preset, "resolution": resolution, "nodes": bases.skin.n_nodes, "members": members,
            "noise_mm": noise, "seed": seed, "with_physics": with_physics, "build_s": built, "kinds": results}


def table(result: dict[str, object]) -> str:
    """The printed tables: per kind, per run and bilateral parameter RMS / max error, median std, RMS z, coverage."""
    lines = []
    for kind, runs in result["kinds"].items():
        if "not_run" in runs:
            lines.append(f"{kind}: not run ({runs['not_run']})")
            continue
        names = list(next(iter(runs.values()))["rms_error_mm"])
        lines += [f"{kind} ({result['preset']} {result['resolution']}, {result['nodes']} nodes, {result['members']} "
                  f"fields, {result['noise_mm']} mm white noise per component): per parameter RMS err / max err / "
                  "median std (mm) / RMS z / 95 % coverage (with model std)",
                  "| estimator | components | ms | " + " | ".join(names) + " | rejected | moved (rejected) |",
                  "|---|---|---|" + "---|" * len(names) + "---|---|"]
        for key, row in runs.items():
            cells = " | ".join(
                f"{row['rms_error_mm'][n]:.1e} / {row['max_error_mm'][n]:.1e} / {row['median_std_mm'][n]:.1e} / "
                f"{row['rms_z'][n]:.2f} / {row['coverage_95'][n]:.0%} ({row['coverage_95_total'][n]:.0%})"
                for n in names)
            lines.append(f"| {key.replace(' ', ' | ')} | {row['estimate_ms_median']:.1f} | {cells} | "
                         f"{row['rejected_share']:.0%} | {row['moved']} ({row['moved_rejected']}) |")
        lines.append("95 % coverage (with model std) of the fields the test passes; moved beyond 2 total std "
                     "(rejected): " + "; ".join(
                         f"{key}: " + " ".join(f"{row['accepted_coverage_95_total'][n]:.0%}" for n in names)
                         + f", {row['moved_total']} ({row['moved_total_rejected']})" for key, row in runs.items()))
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="hood", choices=("hood", "hood-paper"))
    parser.add_argument("--resolution", default="coarse", choices=("coarse", "default", "paper"))
    parser.add_argument("--members", type=int, default=40, help="fields per kind")
    parser.add_argument("--noise", type=float, default=0.01, help="white noise per component, mm")
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=("own",))
    parser.add_argument("--other-models", action="store_true", help="every kind (own and four other models)")
    parser.add_argument("--ccx-cache", type=Path, default=None,
                        help="CalculiX responses (npz, never made here); default: the shared cache of the "
                             "resolution, /work/scratch/cache/standin_ccx_coarse.npz or standin_ccx_default_nopads.npz")
    parser.add_argument("--with-physics", action="store_true",
                        help="bases with the FE model's responses to sheet thickness and gas springs, so the "
                             "contact-aware estimator's model std counts them (bases files carry compliance, pad "
                             "stiffness and preload only)")
    parser.add_argument("--seed", type=int, default=21)
    args = parser.parse_args()
    kinds = KINDS if args.other_models else tuple(args.kinds)
    ccx_cache = args.ccx_cache or CACHE / ("standin_ccx_coarse.npz" if args.resolution == "coarse"
                                           else f"standin_ccx_{args.resolution}_nopads.npz")
    result = run(args.preset, args.resolution, args.members, args.noise, kinds, args.seed, ccx_cache,
                 args.with_physics)
    OUT.mkdir(exist_ok=True)
    suffix = "" if kinds == ("own",) else "_other" if args.other_models else "_" + "_".join(kinds)
    suffix += ("" if kinds == ("own",) and args.noise == 0.01 else f"_noise{args.noise:g}") \
        + ("_physics" if args.with_physics else "")
    path = OUT / f"bench_components_{args.preset}_{args.resolution}{suffix}.json"
    path.write_text(json.dumps(result, indent=1))
    print(table(result))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
