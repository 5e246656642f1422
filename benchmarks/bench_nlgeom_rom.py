"""Benchmark: the reduced geometrically nonlinear model against the full nonlinear solver, and its ensemble time.

On hood-paper (HINGE_Y limited to +-``--hinge-y`` mm: +1 mm buckles the hood, RESULTS.md) the reduced model
(:func:`hood_decomp.core.fe.reduced_geometric.build_reduced_geometric`) is built, the 729 training and 1400 validation
members are solved with it (timed), and ``--check`` validation members plus every 40th training member are solved by
the full nonlinear solver (:class:`hood_decomp.core.fe.geometric.NonlinearSolver`) and compared member by member (the
largest skin translation difference, mm; the pads in contact). ``--hierarchical`` adds the hierarchical basis at
0.1 mm of the nonlinear ensemble (its effects and the largest rank-2 distance from the single effects' span).

Usage: scripts/with-env python benchmarks/bench_nlgeom_rom.py [--resolution coarse|default] [--check 40]
Prints a table and writes benchmarks/out/bench_nlgeom_rom_<resolution>.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=["coarse", "default", "paper"], default="coarse")
    parser.add_argument("--hinge-y", type=float, default=0.5)
    parser.add_argument("--check", type=int, default=40, help="validation members checked against the full solve")
    parser.add_argument("--modes", type=int, default=36)
    parser.add_argument("--hierarchical", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(relativeCreated)8.0f ms %(message)s")
    logging.getLogger("hood_decomp.core.fe.solver").setLevel(logging.WARNING)
    log = logging.getLogger("bench_nlgeom_rom")

    from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble, validation_plan
    from hood_decomp.core.fe.geometric import NonlinearSolver
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.reduced_geometric import build_reduced_geometric
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.types import Ensemble

    out: dict[str, object] = {"resolution": args.resolution, "hinge_y": args.hinge_y, "load_start": os.getloadavg()}
    model = build_preset("hood-paper", args.resolution)
    lower, upper = model.lower.copy(), model.upper.copy()
    j = model.names.index("HINGE_Y")
    lower[j], upper[j] = -args.hinge_y, args.hinge_y
    start = time.perf_counter()
    solver = build_solver(model)
    out["solver_s"] = time.perf_counter() - start
    start = time.perf_counter()
    full = NonlinearSolver(solver)
    out["full_setup_s"] = time.perf_counter() - start
    start = time.perf_counter()
    rom = build_reduced_geometric(solver, lower, upper, modes=args.modes, full=full)
    out["rom_build_s"] = time.perf_counter() - start
    out["modes"], out["pad_shapes"], out["training_residual_mm"] = rom.modes, int(rom.Bf.shape[1]), rom.residual
    log.info("reduced model built in %.1f s", out["rom_build_s"])

    training, rank = factorial_plan(lower, upper)
    validation = validation_plan(lower, upper, 1400, 0)
    start = time.perf_counter()
    block = rom.members(training)
    out["rom_729_s"] = time.perf_counter() - start
    start = time.perf_counter()
    rom.members(validation)
    out["rom_1400_s"] = time.perf_counter() - start
    out["rom_per_member_ms"] = 1000 * (out["rom_729_s"] + out["rom_1400_s"]) / 2129
    log.info("2129 reduced members in %.1f s", out["rom_729_s"] + out["rom_1400_s"])

    checked = np.concatenate([training[::40], validation[:args.check]])
    start = time.perf_counter()
    reduced_members = rom.members(checked)
    full_members = full.members(checked)
    out["full_s_per_member"] = (time.perf_counter() - start) / len(checked)
    diff = np.abs(reduced_members.displacement - full_members.displacement).max(axis=(1, 2))
    normal = np.abs(reduced_members.normal_displacement - full_members.normal_displacement).max(axis=1)
    linear = simulate_ensemble(reduce_model(solver), checked, np.zeros(len(checked)), lower, upper)
    out.update({
        "checked": len(checked), "max_diff_mm": float(diff.max()), "median_diff_mm": float(np.median(diff)),
        "p95_diff_mm": float(np.quantile(diff, 0.95)), "max_normal_diff_mm": float(normal.max()),
        "worst_state": checked[int(diff.argmax())].tolist(),
        "nonlinear_minus_linear_max_mm": float(np.abs(full_members.displacement - linear.displacement).max()),
        "contact_same": bool(np.array_equal(reduced_members.contact_fraction > 0, full_members.contact_fraction > 0)),
    })
    if args.hierarchical:
        from hood_decomp.core.method.hierarchical import HierarchicalBasis

        ensemble = Ensemble(model_id=model.model_id, names=model.names, n_bilateral=len(model.bilateral),
                            lower=lower, upper=upper, commanded=training, effective=block.effective,
                            contact_fraction=block.contact_fraction, reactions=block.reactions, rank=rank,
                            normal_displacement=block.normal_displacement, displacement=block.displacement)
        for epsilon in (0.1, 0.05):
            basis = HierarchicalBasis(epsilon).fit(ensemble)
            out[f"effects_{epsilon}"] = list(basis.effect_names_)
    out["load_end"] = os.getloadavg()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"bench_nlgeom_rom_{args.resolution}.json"
    path.write_text(json.dumps(out, indent=1))
    print("| quantity | value |\n|---|---|")
    for key, value in out.items():
        print(f"| {key} | {value} |")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
