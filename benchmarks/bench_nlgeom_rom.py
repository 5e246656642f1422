"""Benchmark: the reduced geometrically nonlinear model against the full nonlinear solver, and its ensemble time.

On hood-paper (HINGE_Y limited to +-``--hinge-y`` mm: +1 mm buckles the hood, RESULTS.md) the reduced model
(:func:`hood_decomp.core.fe.reduced_geometric.build_reduced_geometric`) is built once per ``--training`` way
(``states``: 137 full solves; ``derivatives``: static derivatives and a few greedy full solves; ``way:TOL``, e.g.
``derivatives:1e-3``: the energy tensors summed over a weighted subset of the facets), its build time split
into its parts (full solves, derivatives, tensors, indicator/check), the 729 training and 1400 validation members are
solved with the first one (timed, ``--no-timing`` skips), and ``--check`` validation members plus every 40th training
member are solved by the full nonlinear solver (:class:`hood_decomp.core.fe.geometric.NonlinearSolver`, once) and
compared member by member with every reduced model (the largest skin translation difference, mm: max, 95th
percentile, median; the pads in contact). ``--hierarchical`` adds the hierarchical basis at 0.1 mm of the first
model's nonlinear ensemble.

Usage: scripts/with-env python benchmarks/bench_nlgeom_rom.py [--resolution coarse|default] [--check 40]
       [--training states,derivatives,derivatives:1e-3]
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
    parser.add_argument("--training", default="states,derivatives",
                        help="comma-separated training ways, each with :TOL to hyper-reduce its energy tensors")
    parser.add_argument("--no-timing", action="store_true", help="skip timing the 2129 reduced members")
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
    trainings = args.training.split(",")
    out["trainings"] = {}
    roms = {}
    for training in trainings:
        start, cpu = time.perf_counter(), time.process_time()
        # its own full solver (set-up in the build time; no tangents shared between the trainings)
        way, _, tolerance = training.partition(":")
        hyper = {"hyper": float(tolerance)} if tolerance else {}  # (without: runs on code before the option too)
        rom = build_reduced_geometric(solver, lower, upper, modes=args.modes, training=way, **hyper)
        roms[training] = rom
        out["trainings"][training] = {
            "build_s": time.perf_counter() - start, "build_cpu_s": time.process_time() - cpu,
            "build_parts_s": rom.build_s, "build_parts_cpu_s": getattr(rom, "build_cpu_s", {}),  # (main: none)
            "modes": rom.modes,
            "pad_shapes": int(rom.Bf.shape[1]), "residual_mm": rom.residual}
        log.info("reduced model (%s) built in %.1f s: %s", training, time.perf_counter() - start, rom.build_s)

    training, rank = factorial_plan(lower, upper)
    validation = validation_plan(lower, upper, 1400, 0)
    first = roms[trainings[0]]
    if not args.no_timing:
        start = time.perf_counter()
        block = first.members(training)
        out["rom_729_s"] = time.perf_counter() - start
        start = time.perf_counter()
        first.members(validation)
        out["rom_1400_s"] = time.perf_counter() - start
        out["rom_per_member_ms"] = 1000 * (out["rom_729_s"] + out["rom_1400_s"]) / 2129
        log.info("2129 reduced members in %.1f s", out["rom_729_s"] + out["rom_1400_s"])

    checked = np.concatenate([training[::40], validation[:args.check]])
    start = time.perf_counter()
    full = NonlinearSolver(solver)
    out["full_setup_s"] = time.perf_counter() - start
    start = time.perf_counter()
    full_members = full.members(checked)
    out["full_s_per_member"] = (time.perf_counter() - start) / len(checked)
    linear = simulate_ensemble(reduce_model(solver), checked, np.zeros(len(checked)), lower, upper)
    out["checked"] = len(checked)
    out["nonlinear_minus_linear_max_mm"] = float(np.abs(full_members.displacement - linear.displacement).max())
    for name, rom in roms.items():
        reduced_members = rom.members(checked)
        diff = np.abs(reduced_members.displacement - full_members.displacement).max(axis=(1, 2))
        normal = np.abs(reduced_members.normal_displacement - full_members.normal_displacement).max(axis=1)
        out["trainings"][name].update({
            "max_diff_mm": float(diff.max()), "median_diff_mm": float(np.median(diff)),
            "p95_diff_mm": float(np.quantile(diff, 0.95)), "max_normal_diff_mm": float(normal.max()),
            "worst_state": checked[int(diff.argmax())].tolist(),
            "contact_same": bool(np.array_equal(reduced_members.contact_fraction > 0,
                                                full_members.contact_fraction > 0))})
    if args.hierarchical:
        if args.no_timing:
            block = first.members(training)
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
        if key != "trainings":
            print(f"| {key} | {value} |")
    keys = ["build_s", "build_cpu_s", "build_parts_s", "build_parts_cpu_s", "modes", "residual_mm", "max_diff_mm",
            "p95_diff_mm", "median_diff_mm", "max_normal_diff_mm", "contact_same", "worst_state"]
    print("\n| training | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for name, row in out["trainings"].items():
        cells = [", ".join(f"{k} {v:.1f}" for k, v in row[k].items()) if isinstance(row[k], dict)
                 else f"{row[k]:.4g}" if isinstance(row[k], float) else str(row[k]) for k in keys]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
