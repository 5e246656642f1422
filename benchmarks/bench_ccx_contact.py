"""Benchmark: hood-paper members (rigid unilateral buffers) against CalculiX, and CalculiX's geometric nonlinearity.

On the coarse hood each pad spring holds one node, so a rigid unilateral buffer is the same constraint in both
solvers. For each member (rank 0, every rank 1, ``--rank23`` random rank-2/3 members):

1. hood_decomp's member (exact LCP on the reduced model) and its contact set (the nodes whose spring pushes);
2. a linear CalculiX job (S8R) with exactly those nodes held at the commanded buffer position and the other pad
   nodes free. By the uniqueness of the contact solution (the compliance is positive definite), that set is
   CalculiX's contact solution too iff the held nodes' reactions push (>= 0) and no free node sinks below its buffer:
   the certificate; the response (member minus the rank-0 member) is compared node by node, as a fraction of its peak:
   the skin normal component (the issue's measure), every translation component against the largest one (the measure
   of ``tests/core/fe/test_calculix.py``'s unit responses), the RMS, and where the worst node lies (the nearest
   boundary site and the edge of the nearest 2 mm reinforcement);
3. geometric nonlinearity: ``--nlgeom N`` members with every buffer node held (no gaps), CalculiX linear against
   NLGEOM; and optionally (``--gaps``) one member with CalculiX's own GAPUNI contact (needs NLGEOM; ~13 min a job
   here).

Usage: scripts/with-env python benchmarks/bench_ccx_contact.py [--rank23 20] [--nlgeom 2] [--gaps]
Prints a table and writes benchmarks/out/bench_ccx_contact.json.
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


def main() -> None:
    from hood_decomp.core.fe.calculix import check_contact_set, run_member_job, write_member_deck
    from hood_decomp.core.fe.ensemble import factorial_plan, solve_members
    from hood_decomp.core.fe.hood_preset import REINFORCEMENT_REACH, build_preset
    from hood_decomp.core.fe.model import patch_nodes, skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", default="coarse", choices=("coarse",),
                        help="coarse only: finer meshes put several nodes on a pad spring")
    parser.add_argument("--rank23", type=int, default=20, help="random rank-2/3 members")
    parser.add_argument("--nlgeom", type=int, default=2, help="members with buffers held, linear vs NLGEOM")
    parser.add_argument("--gaps", action="store_true", help="also one member with ccx GAPUNI contact (slow)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[bench_ccx_contact %(asctime)s] %(message)s")
    log = logging.getLogger("bench_ccx_contact")

    model = build_preset("hood-paper", args.resolution)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    skin = skin_surface(model)
    names = model.names
    commanded, rank = factorial_plan(model.lower, model.upper)
    rng = np.random.default_rng(0)
    pick = np.concatenate([np.flatnonzero(rank <= 1),
                           rng.choice(np.flatnonzero((rank == 2) | (rank == 3)), args.rank23, replace=False)])
    patches = [patch_nodes(model, model.boundary(p.boundary)) for p in model.unilateral]
    if any(len(solver.pads.loads[:, k].indices) != 3 for k in range(len(reduced.k))):
        raise SystemExit("a pad spring holds several nodes: the node-wise comparison needs the coarse hood")

    def ccx_member(state: np.ndarray, **options) -> tuple[np.ndarray, dict[int, np.ndarray], np.ndarray, float]:
        with tempfile.TemporaryDirectory() as directory:
            deck = write_member_deck(model, state, Path(directory) / "deck.inp", **options).read_text()
        start = time.perf_counter()
        u, reactions = run_member_job(deck, len(model.nodes))
        normal = np.einsum("na,na->n", u[model.skin_nodes], skin.normals)
        return normal, reactions, u, time.perf_counter() - start

    sites = {b.name: np.asarray(b.patch.center[:2]) for b in model.boundaries}
    reach = REINFORCEMENT_REACH

    def where(node: int) -> dict[str, object]:
        xy = skin.points[node, :2]
        near = min(sites, key=lambda n: float(np.hypot(*(xy - sites[n]))))
        edge = min(reach, key=lambda n: abs(float(np.hypot(*(xy - sites[n]))) - reach[n]))
        return {"xy_mm": xy.round(1).tolist(), "nearest_site": near,
                "nearest_site_mm": round(float(np.hypot(*(xy - sites[near]))), 1),
                "reinforcement_edge": edge,
                "from_reinforcement_edge_mm": round(float(np.hypot(*(xy - sites[edge]))) - reach[edge], 1)}

    rows = []
    ours_all = solve_members(reduced, commanded[pick])
    reference = None
    for index, member in enumerate(pick):
        state = commanded[member]
        start = time.perf_counter()
        check = check_contact_set(model, state, ours_all.pad_forces[index], skin.normals)
        seconds = time.perf_counter() - start
        ours = ours_all.normal_displacement[index]
        if reference is None:
            assert rank[member] == 0
            reference = (ours, check.normal, ours_all.displacement[index], check.skin_displacement)
        row = {"member": int(member), "rank": int(rank[member]),
               "setting": {n: float(v) for n, v in zip(names, state, strict=True) if v != 0}, "ccx_s": seconds}
        response_ours, response_ccx = ours - reference[0], check.normal - reference[1]
        peak = float(np.abs(response_ours).max())
        row["response_peak_mm"] = peak
        row["response_max_diff_mm"] = float(np.abs(response_ccx - response_ours).max())
        row["response_diff_of_peak"] = row["response_max_diff_mm"] / peak if peak > 0 else float("nan")
        row["response_rms_diff_of_peak"] = float(np.sqrt(np.mean((response_ccx - response_ours) ** 2)) / peak
                                                 if peak > 0 else float("nan"))
        vector_ours = ours_all.displacement[index] - reference[2]
        vector_ccx = check.skin_displacement - reference[3]
        peak_3d = float(np.abs(vector_ours).max())
        row["response_3d_peak_mm"] = peak_3d
        row["response_3d_diff_of_peak"] = (float(np.abs(vector_ccx - vector_ours).max()) / peak_3d if peak_3d > 0
                                           else float("nan"))
        row["worst_node"] = where(int(np.argmax(np.abs(response_ccx - response_ours))))
        row["member_max_diff_of_peak"] = float(np.abs(check.normal - ours).max() / np.abs(ours).max())
        row.update(lifted=[not t.any() for t in check.touching],
                   held_reaction_min_N=check.held_reaction_min.tolist(), free_gap_min_mm=check.free_gap_min.tolist(),
                   reaction_ccx_vs_ours_N=list(zip(check.reaction.tolist(), ours_all.reactions[index].tolist(),
                                                   strict=True)))
        # certified: no held node pulls by more than 2 % of the largest buffer load (a contact edge, node-wise) and
        # no free node sinks below its buffer by 1e-3 mm
        row["contact_certified"] = check.certified(0.02 * max(float(ours_all.reactions[index].max()), 1.0))
        rows.append(row)
        log.info("member %d (rank %d) %s: response diff %.2f %% of %.3f mm, certified %s, %.0f s", member,
                 rank[member], row["setting"], 100 * row["response_diff_of_peak"], peak, row["contact_certified"],
                 seconds)

    nonlinear = []
    for state in ([0.0] * len(names), [0.0, -1.0, -1.0, 1.0, 1.0, 0.0])[: args.nlgeom]:
        state = np.array(state)
        linear, _, _, t_lin = ccx_member(state, buffers="held", nlgeom=False)
        geometric, _, _, t_nl = ccx_member(state, buffers="held", nlgeom=True)
        nonlinear.append({"setting": {n: float(v) for n, v in zip(names, state, strict=True) if v != 0},
                          "linear_peak_mm": float(np.abs(linear).max()),
                          "nlgeom_minus_linear_max_mm": float(np.abs(geometric - linear).max()),
                          "linear_s": t_lin, "nlgeom_s": t_nl})
        log.info("NLGEOM %s: %.4f mm of %.3f mm", nonlinear[-1]["setting"], nonlinear[-1]["nlgeom_minus_linear_max_mm"],
                 nonlinear[-1]["linear_peak_mm"])
    gaps = None
    if args.gaps:
        state = np.zeros(len(names))
        state[names.index("BUFFER_L")] = 1.0
        member = solve_members(reduced, state[None, :])
        normal, reactions, _, seconds = ccx_member(state, buffers="unilateral", nlgeom=True)
        gaps = {"setting": {"BUFFER_L": 1.0},
                "max_diff_mm": float(np.abs(normal - member.normal_displacement[0]).max()),
                "peak_mm": float(np.abs(member.normal_displacement[0]).max()),
                "reaction_ccx_N": float(sum(reactions[n][2] for n in patches[0])),
                "reaction_ours_N": float(member.reactions[0, 0]), "ccx_s": seconds}
    result = {"resolution": args.resolution, "members": rows, "nlgeom": nonlinear, "gapuni": gaps}
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "bench_ccx_contact.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print("| member | rank | setting | normal response peak (mm) | max diff (% of peak) | RMS diff (%) | "
          "3D: peak (mm), max diff (%) | worst node: nearest site, from reinforcement edge (mm) | "
          "lifted (ours = ccx) | reaction ccx / ours (N) |\n|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        certified = "certified" if row["contact_certified"] else "NOT certified"
        worst = row["worst_node"]
        print(f"| {row['member']} | {row['rank']} | {row['setting']} | {row['response_peak_mm']:.3f} | "
              f"{100 * row['response_diff_of_peak']:.2f} | {100 * row['response_rms_diff_of_peak']:.2f} | "
              f"{row['response_3d_peak_mm']:.3f}, {100 * row['response_3d_diff_of_peak']:.2f} | "
              f"{worst['nearest_site']} {worst['nearest_site_mm']:.0f} mm, {worst['reinforcement_edge']} "
              f"{worst['from_reinforcement_edge_mm']:+.0f} | {row['lifted']} {certified} | "
              + ", ".join(f"{a:.0f}/{b:.0f}" for a, b in row["reaction_ccx_vs_ours_N"]) + " |")
    for entry in nonlinear:
        print(f"NLGEOM - linear, buffers held, {entry['setting']}: {entry['nlgeom_minus_linear_max_mm']:.4f} mm "
              f"(linear peak {entry['linear_peak_mm']:.3f} mm)")
    if gaps:
        print(f"GAPUNI + NLGEOM {gaps['setting']}: max diff {gaps['max_diff_mm']:.4f} mm of {gaps['peak_mm']:.3f}")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
