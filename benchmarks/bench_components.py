"""Benchmark: fitting all three displacement components against the normal one (issue 21, ``components="xyz"``).

Through the product's path (bases, ``estimate_field``) on one preset and resolution: ``--members`` random states
of the model (validation plan, seed 11; the reduced model's own 3D member fields), each with one draw of white noise
of ``--noise`` mm on every component (seed 0; the normal values the normal part of the same noisy vectors, no
error model: a simulated field), estimated by both estimators with both component sets. Per run: the median
estimate time (ms; the estimator prepared first, its time apart), per bilateral parameter the RMS error against the
state (mm) and the RMS of error / stated std, and the share of fields the within-model test rejects (the fields are
the model's: that share is the false-alarm rate, alpha 0.01).

Usage: scripts/with-env python benchmarks/bench_components.py [--preset hood|hood-paper] [--resolution coarse]
       [--members 40] [--noise 0.01]
Prints a table and writes benchmarks/out/bench_components_<preset>_<resolution>.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_partial_contact import bases_of

OUT = Path(__file__).resolve().parent / "out"


def run(preset: str, resolution: str, members: int, noise: float) -> dict[str, object]:
    from hood_decomp.core.fe.ensemble import solve_members, validation_plan
    from hood_decomp.core.method.bases import estimate_field
    from hood_decomp.core.types import DisplacementField

    started = time.perf_counter()
    bases, reduced = bases_of(preset, resolution)
    built = time.perf_counter() - started
    normals = bases.skin.normals
    plan = validation_plan(bases.pca.lower_, bases.pca.upper_, members, seed=11)
    block = solve_members(reduced, plan)
    rng = np.random.default_rng(0)
    fields = []
    for vectors in block.displacement:
        noisy = vectors + rng.normal(0.0, noise, vectors.shape)
        fields.append(DisplacementField(bases.model_id, np.einsum("na,na->n", noisy, normals), 1.0, float("nan"),
                                        displacement=noisy))
    n_b = reduced.n_bilateral
    runs = {}
    for method in ("contact", "pca"):
        for components in ("normal", "xyz"):
            tic = time.perf_counter()
            bases.prepare_estimation(method, 0.2, 0.0, components)
            prepare = time.perf_counter() - tic
            times, errors, z, rejected = [], [], [], 0
            for field, truth in zip(fields, block.effective, strict=True):
                tic = time.perf_counter()
                estimate = estimate_field(bases, field, method, components=components)
                times.append(time.perf_counter() - tic)
                errors.append(estimate.values[:n_b] - truth[:n_b])
                z.append(errors[-1] / estimate.std[:n_b])
                rejected += not estimate.within_model
            runs[f"{method} {components}"] = {
                "prepare_s": prepare, "estimate_ms_median": 1e3 * float(np.median(times)),
                "rms_error_mm": dict(zip(reduced.names[:n_b], np.sqrt(np.mean(np.square(errors), axis=0)).tolist(),
                                         strict=True)),
                "rms_z": dict(zip(reduced.names[:n_b], np.sqrt(np.mean(np.square(z), axis=0)).tolist(), strict=True)),
                "rejected_share": rejected / members}
    return {"preset": preset, "resolution": resolution, "nodes": bases.skin.n_nodes, "members": members,
            "noise_mm": noise, "build_s": built, "runs": runs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="hood", choices=("hood", "hood-paper"))
    parser.add_argument("--resolution", default="coarse", choices=("coarse", "default", "paper"))
    parser.add_argument("--members", type=int, default=40)
    parser.add_argument("--noise", type=float, default=0.01)
    args = parser.parse_args()
    result = run(args.preset, args.resolution, args.members, args.noise)
    OUT.mkdir(exist_ok=True)
    path = OUT / f"bench_components_{args.preset}_{args.resolution}.json"
    path.write_text(json.dumps(result, indent=1))
    names = list(next(iter(result["runs"].values()))["rms_error_mm"])
    print(f"{args.preset} {args.resolution} ({result['nodes']} nodes): {args.members} members, {args.noise} mm white "
          "noise per component")
    print("| estimator | components | estimate (ms, median) | prepare (s) | "
          + " | ".join(f"{n} RMS err (mm) / RMS z" for n in names) + " | rejected |")
    print("|---|---|---|---|" + "---|" * len(names) + "---|")
    for key, row in result["runs"].items():
        cells = " | ".join(f"{row['rms_error_mm'][n]:.2e} / {row['rms_z'][n]:.2f}" for n in names)
        print(f"| {key.replace(' ', ' | ')} | {row['estimate_ms_median']:.1f} | {row['prepare_s']:.3f} | {cells} | "
              f"{row['rejected_share']:.0%} |")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
