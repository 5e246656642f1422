"""Benchmark: the contact-aware estimator on buffers that touch on only some of their pad springs (issue 21).

Two checks on one preset and resolution, through the product's path (bases, ``estimate_field``):

- noise-free: ``--members`` random members of the estimator's own model (validation plan, seed 0; no noise stated),
  max |estimate - observable state| per parameter (a lifted buffer's observable state is the part's position there)
  and the number of wrong lifted flags; the estimate must be exact on every contact state, partial contact included;
- noisy light touch: the members whose buffer touches on 1-3 springs with ``--force-range`` N in all, each with
  ``--draws`` draws of white node noise (``--noise`` mm, stated): per bilateral state the RMS of error / stated std,
  the largest |error| / std and the share inside the 95 % interval (truth: the commanded bilateral states).

Usage: scripts/with-env python benchmarks/bench_partial_contact.py [--preset hood-paper|hood] [--resolution coarse]
       [--members 200] [--draws 30] [--noise 0.02] [--force-range 1 5]
Prints a table and writes benchmarks/out/bench_partial_contact_<preset>_<resolution>.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"


def bases_of(preset: str, resolution: str):
    """(bases, reduced model) of a preset: the full-factorial ensemble and its bases, as ``hood-decomp bases`` does."""
    from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.method.bases import build_bases

    model = build_preset(preset, resolution)
    reduced = reduce_model(build_solver(model))
    commanded, rank = factorial_plan(model.lower, model.upper)
    ensemble = simulate_ensemble(reduced, commanded, rank, model.lower, model.upper)
    return build_bases(ensemble, skin_surface(model), reduced), reduced


def observable(reduced, state: np.ndarray, forces: np.ndarray) -> np.ndarray:
    """(P,) mm: the state, a lifted buffer's value replaced by the part's position there (min over its springs of
    z - preload: the commanded position at which it would just touch)."""
    B = reduced.n_bilateral
    values = state.copy()
    z = reduced.z0 + reduced.Sa @ state[:B] + reduced.H @ forces
    for u in range(state.size - B):
        springs = reduced.pad_of == u
        if not (forces[springs] > 0).any():
            values[B + u] = np.min(z[springs] - reduced.preload[springs])
    return values


def run(preset: str, resolution: str, members: int, draws: int, noise: float, force_range: tuple[float, float]
        ) -> dict[str, object]:
    from hood_decomp.core.fe.ensemble import solve_members, validation_plan
    from hood_decomp.core.method.bases import estimate_field
    from hood_decomp.core.types import DisplacementField

    log = logging.getLogger("bench_partial_contact")
    t = time.perf_counter()
    bases, reduced = bases_of(preset, resolution)
    build_s = time.perf_counter() - t
    names = list(reduced.names)
    B, U = reduced.n_bilateral, len(names) - reduced.n_bilateral
    plan = validation_plan(bases.pca.lower_, bases.pca.upper_, members)
    block = solve_members(reduced, plan)
    touching = np.array([[(block.pad_forces[i][reduced.pad_of == u] > 0).sum() for u in range(U)]
                         for i in range(members)])
    force = np.array([[block.pad_forces[i][reduced.pad_of == u].sum() for u in range(U)] for i in range(members)])
    per_pad = np.bincount(reduced.pad_of, minlength=U)

    errors, wrong = [], 0
    t = time.perf_counter()
    for i in range(members):
        field = DisplacementField(bases.model_id, block.normal_displacement[i], 1.0, float("nan"))
        estimate = estimate_field(bases, field)
        errors.append(estimate.values - observable(reduced, plan[i], block.pad_forces[i]))
        wrong += int(np.sum(estimate.lifted[B:] != (touching[i] == 0)))
        if (i + 1) % 50 == 0:
            log.info("noise-free: %d of %d", i + 1, members)
    noise_free_s = (time.perf_counter() - t) / members
    errors = np.abs(np.array(errors))

    light = np.flatnonzero(((touching >= 1) & (touching <= 3) & (force >= force_range[0])
                            & (force <= force_range[1])).any(axis=1))
    rng = np.random.default_rng(5)
    z = []
    for i in light:
        for _ in range(draws):
            noisy = block.normal_displacement[i] + rng.normal(0.0, noise, block.normal_displacement.shape[1])
            estimate = estimate_field(bases, DisplacementField(bases.model_id, noisy, 1.0, noise))
            z.append((estimate.values[:B] - plan[i, :B]) / estimate.std[:B])
    z = np.array(z).reshape(-1, B)
    return {
        "preset": preset, "resolution": resolution, "members": members, "build_s": build_s,
        "noise_free": {
            "partial_contact_pads": int(np.sum((touching > 0) & (touching < per_pad[None, :]))),
            "pads_touching_on_1_to_3_springs": int(np.sum((touching >= 1) & (touching <= 3))),
            "wrong_lifted_flags": wrong,
            "max_abs_error_mm": dict(zip(names, errors.max(axis=0).tolist(), strict=True)),
            "seconds_per_estimate": noise_free_s,
        },
        "noisy_light_touch": {
            "members": light.tolist(), "draws": draws, "noise_mm": noise, "force_range_n": list(force_range),
            "rms_z": dict(zip(names[:B], np.sqrt(np.mean(z**2, axis=0)).tolist(), strict=True)) if z.size else {},
            "max_abs_z": dict(zip(names[:B], np.abs(z).max(axis=0).tolist(), strict=True)) if z.size else {},
            "inside_95": dict(zip(names[:B], np.mean(np.abs(z) <= 1.959964, axis=0).tolist(), strict=True))
            if z.size else {},
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="hood-paper", choices=("hood-paper", "hood"))
    parser.add_argument("--resolution", default="coarse", choices=("coarse", "default", "paper"))
    parser.add_argument("--members", type=int, default=200)
    parser.add_argument("--draws", type=int, default=30)
    parser.add_argument("--noise", type=float, default=0.02, help="white node noise (mm) of the light-touch check")
    parser.add_argument("--force-range", type=float, nargs=2, default=(1.0, 5.0), metavar=("LOW", "HIGH"),
                        help="total force (N) of a light-touch buffer")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    result = run(args.preset, args.resolution, args.members, args.draws, args.noise, tuple(args.force_range))
    OUT.mkdir(exist_ok=True)
    path = OUT / f"bench_partial_contact_{args.preset}_{args.resolution}.json"
    path.write_text(json.dumps(result, indent=1))
    free, noisy = result["noise_free"], result["noisy_light_touch"]
    print(f"{args.preset} {args.resolution}: {args.members} noise-free members, {free['partial_contact_pads']} "
          f"pads in partial contact ({free['pads_touching_on_1_to_3_springs']} on 1-3 springs), "
          f"{free['wrong_lifted_flags']} wrong lifted flags")
    print("| parameter | noise-free max |error| (mm) | light touch: RMS z | max |z| | inside 95 % |")
    print("|---|---|---|---|---|")
    for name, error in free["max_abs_error_mm"].items():
        cells = [f"{noisy[key][name]:.2f}" if name in noisy[key] else "-" for key in ("rms_z", "max_abs_z")]
        inside = f"{100 * noisy['inside_95'][name]:.1f} %" if name in noisy["inside_95"] else "-"
        print(f"| {name} | {error:.1e} | {cells[0]} | {cells[1]} | {inside} |")
    print(f"light touch: {len(noisy['members'])} members x {noisy['draws']} draws at {noisy['noise_mm']} mm; "
          f"JSON: {path}")


if __name__ == "__main__":
    main()
