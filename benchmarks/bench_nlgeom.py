"""Benchmark: geometric nonlinearity of hood-paper, hood_decomp's initial-stress solve against CalculiX NLGEOM.

On the coarse hood-paper with every buffer node held at its commanded position (no contact, as
``bench_ccx_contact.py --nlgeom``), each member is solved four ways: CalculiX S8R linear and NLGEOM, and hood_decomp's
linear and geometrically nonlinear solve (:func:`hood_decomp.core.fe.geometric.solve_nonlinear`). The row compares
the nonlinear-minus-linear skin normal field of both solvers. CalculiX translations are cached in
benchmarks/out/ccx_nlgeom_<state>.npz (a NLGEOM job takes 10-12 min on the shared machine).

It also gives HINGE_Y's linear buckling factor (the hinge motion alone), CalculiX *BUCKLE against
:func:`hood_decomp.core.fe.geometric.buckling_factor`, and (``--ensemble``) the 729 training members linear and
nonlinear with the hierarchical basis at 0.1 mm (HINGE_Y limited to ``--hinge-y``: the coarse hood buckles at +0.9 mm).

Usage: scripts/with-env python benchmarks/bench_nlgeom.py [--ccx-only | --ensemble [--hinge-y 0.5]]
Prints a table and writes benchmarks/out/bench_nlgeom.json (bench_nlgeom_ensemble.json).
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"
#: members with the buffers held (model.names order: HINGE_X, HINGE_Y, LOCK_L, LOCK_R, BUFFER_L, BUFFER_R)
STATES = ((0.0, -1.0, -1.0, 1.0, 1.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0, 0.0))


def ccx_path(model, state: np.ndarray) -> Path:
    """Where the CalculiX translations of a member are cached."""
    return OUT / f"ccx_nlgeom_{model.model_id}_{'_'.join(f'{v:+.2f}' for v in state)}.npz"


def ccx_fields(model, state: np.ndarray, log: logging.Logger) -> dict[str, np.ndarray]:
    """CalculiX translations (n, 3) mm, linear and NLGEOM, of a member with all buffer nodes held (cached)."""
    from hood_decomp.core.fe.calculix import run_member_job, write_member_deck

    tag = "_".join(f"{v:+.2f}" for v in state)
    path = ccx_path(model, state)
    if path.exists():
        return dict(np.load(path))
    out = {}
    for key, nlgeom in (("linear", False), ("nlgeom", True)):
        with tempfile.TemporaryDirectory() as directory:
            deck = write_member_deck(model, state, Path(directory) / "deck.inp", buffers="held", nlgeom=nlgeom)
            text = deck.read_text()
        start = time.perf_counter()
        out[key], _ = run_member_job(text, len(model.nodes))
        out[f"{key}_s"] = np.array(time.perf_counter() - start)
        log.info("ccx %s %s: %.0f s", key, tag, float(out[f"{key}_s"]))
    OUT.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)
    return out


def ensemble_study(log: logging.Logger, hinge_y: float) -> dict:
    """The coarse hood-paper's 729 training members, linear and geometrically nonlinear, with HINGE_Y in
    [-hinge_y, hinge_y]: the rank-2 distance from the loads' + single effects' span, the interaction map and the
    greedy hierarchical basis at 0.1 mm for both (the nonlinear members cached in benchmarks/out)."""
    from dataclasses import replace

    from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble
    from hood_decomp.core.fe.geometric import NonlinearSolver, nonlinear_ensemble
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.method.hierarchical import HierarchicalBasis
    from hood_decomp.core.method.interactions import interaction_map

    model = build_preset("hood-paper", "coarse")
    model = replace(model, parameters=tuple(replace(p, lower=-hinge_y, upper=hinge_y) if p.label == "HINGE_Y" else p
                                            for p in model.parameters))
    commanded, rank = factorial_plan(model.lower, model.upper)
    solver = build_solver(model)
    linear = simulate_ensemble(reduce_model(solver), commanded, rank, model.lower, model.upper)
    start = time.perf_counter()
    nonlinear_solver = NonlinearSolver(solver, tolerance=1e-5, contraction=0.2)
    setup_s = time.perf_counter() - start
    nonlinear = nonlinear_ensemble(nonlinear_solver, commanded, rank, model.lower, model.upper)
    members_s = time.perf_counter() - start - setup_s
    log.info("nonlinear ensemble: setup %.0f s, %d members %.0f s, %d tangents", setup_s, len(commanded), members_s,
             nonlinear_solver.factorisations)
    np.savez(OUT / "nl_ensemble_coarse.npz", normal=nonlinear.normal_displacement, commanded=commanded, rank=rank)
    out = {"hinge_y_range_mm": hinge_y, "setup_s": setup_s, "members_s": members_s, "members": len(commanded),
           "tangents": nonlinear_solver.factorisations}
    for name, ensemble in (("linear", linear), ("nonlinear", nonlinear)):
        x = ensemble.normal_displacement
        span = np.vstack([x[rank == 0], x[rank == 1] - x[rank == 0]])
        rank2 = x[rank == 2]
        coefficients = np.linalg.lstsq(span.T, rank2.T, rcond=None)[0]
        distance = np.abs(rank2 - coefficients.T @ span).max(axis=1)
        worst = np.flatnonzero(rank == 2)[int(np.argmax(distance))]
        found = interaction_map(ensemble)
        basis = HierarchicalBasis(0.1).fit(ensemble)
        out[name] = {"rank2_distance_max_mm": float(distance.max()),
                     "rank2_worst": {n: float(v) for n, v in zip(model.names, commanded[worst], strict=True) if v},
                     "rank2_above_0.1": int((distance > 0.1).sum()),
                     "interaction_pair_peak_mm": np.nan_to_num(found.pair_peak_mm).tolist(),
                     "effects": list(basis.effect_names_), "effect_ranks": basis.effect_rank_.tolist()}
        log.info("%s: rank-2 distance %.4f mm (%s), effects %s", name, distance.max(), out[name]["rank2_worst"],
                 basis.effect_names_)
    out["nonlinear_minus_linear_max_mm"] = float(np.abs(nonlinear.normal_displacement
                                                        - linear.normal_displacement).max())
    return out


def main() -> None:
    from hood_decomp.core.fe.geometric import NonlinearSolver
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.model import AXES, patch_nodes, skin_surface
    from hood_decomp.core.fe.solver import build_solver

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ccx-only", action="store_true", help="only run (and cache) the CalculiX jobs")
    parser.add_argument("--ensemble", action="store_true", help="only the nonlinear ensemble study")
    parser.add_argument("--hinge-y", type=float, default=0.5,
                        help="HINGE_Y range (mm) of the ensemble study: +0.90 mm buckles the coarse hood")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[bench_nlgeom %(asctime)s] %(message)s")
    log = logging.getLogger("bench_nlgeom")
    if args.ensemble:
        result = ensemble_study(log, args.hinge_y)
        (OUT / "bench_nlgeom_ensemble.json").write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps({k: v for k, v in result.items() if k not in ("linear", "nonlinear")}))
        for name in ("linear", "nonlinear"):
            print(name, {k: v for k, v in result[name].items() if k != "interaction_pair_peak_mm"})
        return
    model = build_preset("hood-paper", "coarse")
    if args.ccx_only:
        for state in STATES:
            ccx_fields(model, np.array(state), log)
        return
    held = held_buffers(model)
    solver = build_solver(held)
    start = time.perf_counter()
    nonlinear = NonlinearSolver(solver, tolerance=1e-6, contraction=0.2)
    normals = skin_surface(model).normals
    skin = model.skin_nodes
    rows = []
    for state in STATES:
        state = np.array(state)
        if not ccx_path(model, state).exists():
            log.info("no CalculiX result for %s yet (run --ccx-only): skipped", state)
            continue
        ccx = ccx_fields(model, state, log)
        prescribed = np.zeros(len(solver.constrained))
        for parameter, value in zip(held.parameters, state, strict=True):
            dofs = 6 * patch_nodes(held, held.boundary(parameter.boundary)) + AXES[parameter.direction]
            prescribed[np.isin(solver.constrained, dofs)] = value
        ours_linear = solver.solve(solver.load, prescribed).reshape(-1, 6)[skin, :3]
        ours_nl = nonlinear.solve(state[None, :]).translations[0][skin]
        normal = {key: np.einsum("na,na->n", field, normals) for key, field in
                  (("ccx_linear", ccx["linear"][skin]), ("ccx_nlgeom", ccx["nlgeom"][skin]),
                   ("ours_linear", ours_linear), ("ours_nl", ours_nl))}
        effect_ccx = normal["ccx_nlgeom"] - normal["ccx_linear"]
        effect_ours = normal["ours_nl"] - normal["ours_linear"]
        row = {"setting": {n: float(v) for n, v in zip(model.names, state, strict=True) if v},
               "ccx_linear_peak_mm": float(np.abs(normal["ccx_linear"]).max()),
               "ours_linear_peak_mm": float(np.abs(normal["ours_linear"]).max()),
               "ccx_nl_minus_linear_max_mm": float(np.abs(effect_ccx).max()),
               "ours_nl_minus_linear_max_mm": float(np.abs(effect_ours).max()),
               "effect_difference_max_mm": float(np.abs(effect_ours - effect_ccx).max()),
               "effect_correlation": float(np.corrcoef(effect_ours, effect_ccx)[0, 1]),
               "nl_member_difference_max_mm": float(np.abs(normal["ours_nl"] - normal["ccx_nlgeom"]).max()),
               "linear_member_difference_max_mm": float(np.abs(normal["ours_linear"] - normal["ccx_linear"]).max()),
               "ccx_nlgeom_s": float(ccx["nlgeom_s"])}
        rows.append(row)
        log.info("%s", row)
    result = {"held_buffers": rows, "ours_s": time.perf_counter() - start,
              "hinge_y_buckling": buckling(model, held, log)}
    (OUT / "bench_nlgeom.json").write_text(json.dumps(result, indent=2) + "\n")
    print("| setting | linear peak ccx / ours (mm) | NL - linear ccx (mm) | NL - linear ours (mm) | difference of the "
          "two (mm) | correlation | NL member ours - ccx (mm) |\n|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['setting'] or 'nominal'} | {r['ccx_linear_peak_mm']:.3f} / {r['ours_linear_peak_mm']:.3f} | "
              f"{r['ccx_nl_minus_linear_max_mm']:.4f} | {r['ours_nl_minus_linear_max_mm']:.4f} | "
              f"{r['effect_difference_max_mm']:.4f} | {r['effect_correlation']:.3f} | "
              f"{r['nl_member_difference_max_mm']:.4f} |")
    print(f"HINGE_Y linear buckling factor: {result['hinge_y_buckling']}")


def buckling(model, held, log: logging.Logger) -> dict:
    """HINGE_Y's linear buckling factor (the hinge motion alone, no loads): CalculiX *BUCKLE (S8R, buffers held;
    cached) and hood_decomp's :func:`buckling_factor` with the buffers held and free."""
    from dataclasses import replace

    from hood_decomp.core.fe.calculix import _run_ccx, write_member_deck
    from hood_decomp.core.fe.geometric import buckling_factor
    from hood_decomp.core.fe.solver import build_solver

    path = OUT / f"ccx_buckle_hinge_y_{model.model_id}.json"
    if not path.exists():
        quiet = replace(model, gravity=np.zeros(3), boundaries=tuple(
            replace(b, force=1e-9) if b.kind == "force" else b for b in model.boundaries))
        state = np.zeros(len(model.names))
        state[model.names.index("HINGE_Y")] = 1.0
        with tempfile.TemporaryDirectory() as directory:
            text = write_member_deck(quiet, state, Path(directory) / "deck.inp", buffers="held", nlgeom=False
                                     ).read_text().replace("*STEP\n*STATIC", "*STEP\n*BUCKLE\n3", 1)
            text = "\n".join(line for line in text.split("*NODE PRINT")[0].splitlines()) + "\n*END STEP\n"
            start = time.perf_counter()
            dat = _run_ccx(text, "buckle", directory, 3600.0, None).with_suffix(".dat").read_text()
        block = dat[dat.index("B U C K L I N G"):].splitlines()
        factors = [float(line.split()[1]) for line in block if line.split()[:1] and line.split()[0].isdigit()][:3]
        path.write_text(json.dumps({"factors": factors, "seconds": time.perf_counter() - start}) + "\n")
    ccx = json.loads(path.read_text())
    out = {"ccx_held": ccx["factors"], "ccx_s": ccx["seconds"]}
    for name, part in (("ours_held", held), ("ours_free", model)):
        solver = build_solver(part)
        out[name] = buckling_factor(solver, solver.boundary_response("hinge_L", "y"))
    log.info("HINGE_Y buckling factor: %s", out)
    return out


def held_buffers(model):
    """The model with every buffer a bilateral prescribed boundary along its axis (Z) over its whole patch, as
    ``write_member_deck(buffers="held")`` holds it."""
    from dataclasses import replace

    return replace(model, boundaries=tuple(replace(b, kind="prescribed", dofs=("z",)) if b.kind == "unilateral"
                                           else b for b in model.boundaries))


if __name__ == "__main__":
    main()
