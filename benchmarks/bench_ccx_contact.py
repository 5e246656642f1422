"""Benchmark: hood-paper members (rigid unilateral buffers) against CalculiX, and CalculiX's geometric nonlinearity.

For each member (rank 0, every rank 1, ``--rank23`` random rank-2/3 members):

1. hood_decomp's member (exact LCP on the reduced model) and its contact set (the pad springs that push);
2. a linear CalculiX job (S8R) holding exactly those springs at the commanded buffer position as the embedded solver's
   rigid springs do (each an ``*EQUATION`` on the area-weighted mean of its nodes; on the coarse hood one node a
   spring) and the other springs free. By the uniqueness of the contact solution (the compliance is positive
   definite), that set is CalculiX's contact solution too iff the held springs push (>= 0) and no free spring sinks
   below its buffer: the certificate; the response (member minus the rank-0 member) is compared node by node, as a
   fraction of its peak: the skin normal component (the issue's measure), every translation component against the
   largest one (the measure of ``tests/core/fe/test_calculix.py``'s unit responses), the RMS, and where the worst
   node lies (the nearest boundary site and the edge of the nearest 2 mm reinforcement);
3. geometric nonlinearity: ``--nlgeom N`` members with every buffer node held (no gaps), CalculiX linear against
   NLGEOM; and optionally (``--gaps``) one member with CalculiX's own GAPUNI contact (needs NLGEOM; ~13 min a job
   here).

``--spot`` instead compares the members of :data:`SPOT` (the rank-0 member, the worst coarse misses, three of rank
2/3) on every mesh of ``--grids`` (default: 44 x 51, coarse, 101 x 117, default), each mesh with its own rigid pad
springs in both solvers, and fits the order p of each difference, d ~ h^p (h: the skin grid's mean spacing). CalculiX
jobs are cached in ``--cache`` (one .npz per model, member and contact set) so the default-resolution spot check is
one command that reads them; a missing job on a mesh of more than :data:`LOCKED_SKIN_NODES` skin nodes (~7.7 GB, 4-7
min) runs only while holding ``--lock`` (flock), so such jobs run one at a time across users.

Usage: scripts/with-env python benchmarks/bench_ccx_contact.py [--rank23 20] [--nlgeom 2] [--gaps] [--cache DIR]
       scripts/with-env python benchmarks/bench_ccx_contact.py --spot --cache DIR [--lock FILE] [--grids ...]
Prints a table and writes benchmarks/out/bench_ccx_contact.json (``--spot``: bench_ccx_contact_spot.json).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"
#: the spot-check members: rank 0, the worst coarse misses of rank 1 and rank 2/3 (session 9), BUFFER_L +1 alone
SPOT = ({}, {"LOCK_L": -1.0}, {"LOCK_L": -1.0, "BUFFER_L": 1.0}, {"LOCK_R": -1.0, "BUFFER_L": 1.0, "BUFFER_R": 1.0},
        {"HINGE_X": 1.0, "LOCK_L": -1.0, "BUFFER_R": 1.0}, {"BUFFER_L": 1.0}, {"HINGE_X": 1.0})
#: meshes of more skin nodes than this (the default hood: 30,107) run CalculiX only while holding the lock
LOCKED_SKIN_NODES = 20000

log = logging.getLogger("bench_ccx_contact")


def cached_check(model, state: np.ndarray, pad_forces: np.ndarray, normals: np.ndarray, cache: Path | None,
                 lock: Path | None, cache_only: bool = False):
    """:func:`check_contact_set` of a member, read from ``cache`` when a job of the same model, state and held springs
    is there, else run (under ``lock`` on large meshes) and stored. Returns (ContactCheck, ccx seconds, from cache);
    with ``cache_only`` a job not in the cache is (None, nan, False)."""
    from hood_decomp.core.fe.calculix import ContactCheck, check_contact_set, holding

    held = np.asarray(pad_forces) > 0
    key = hashlib.sha1(np.concatenate([np.round(state, 9), held]).tobytes()).hexdigest()[:12]
    path = None if cache is None else cache / f"ccx_member_{model.name}_{key}.npz"
    if path is not None and path.exists():
        data = np.load(path)
        touching = tuple(np.split(data["touching"], np.cumsum(data["touching_sizes"])[:-1]))
        fields = {f: data[f] for f in ("normal", "skin_displacement", "spring_reaction", "spring_gap", "reaction",
                                       "held_reaction_min", "free_gap_min")}
        return ContactCheck(touching=touching, **fields), float(data["seconds"]), True
    if cache_only:
        log.warning("--cache-only: no cached CalculiX job %s (%s, state %s)", path, model.name, state.tolist())
        return None, float("nan"), False
    large = len(model.skin_nodes) > LOCKED_SKIN_NODES
    with holding(lock if large else None):
        start = time.perf_counter()
        check = check_contact_set(model, state, pad_forces, normals)
        seconds = time.perf_counter() - start
    log.info("ccx %s %s: %.0f s", model.name, state.tolist(), seconds)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, normal=check.normal, skin_displacement=check.skin_displacement,
                 spring_reaction=check.spring_reaction, spring_gap=check.spring_gap, reaction=check.reaction,
                 held_reaction_min=check.held_reaction_min, free_gap_min=check.free_gap_min,
                 touching=np.concatenate(check.touching), touching_sizes=[len(t) for t in check.touching],
                 seconds=seconds, state=state, held=held)
    return check, seconds, False


def compare(model, states: np.ndarray, cache: Path | None, lock: Path | None, cache_only: bool = False) -> list[dict]:
    """Solve ``states`` (m, P) (the first: the rank-0 member) with hood_decomp and CalculiX; one row per member."""
    from hood_decomp.core.fe.ensemble import solve_members
    from hood_decomp.core.fe.hood_preset import REINFORCEMENT_REACH
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.fe.solver import build_solver, reduce_model

    assert not states[0].any(), "the first member is the rank-0 member"
    start = time.perf_counter()
    reduced = reduce_model(build_solver(model))  # the factorised solver is dropped here: memory for ccx
    ours_all = solve_members(reduced, states)
    log.info("%s: ours %.0f s (%d skin nodes, %d pad springs)", model.name, time.perf_counter() - start,
             len(model.skin_nodes), len(reduced.k))
    skin = skin_surface(model)
    names = model.names
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
    reference = None
    for index, state in enumerate(states):
        check, seconds, cached = cached_check(model, state, ours_all.pad_forces[index], skin.normals, cache, lock,
                                              cache_only)
        row = {"model": model.name, "setting": {n: float(v) for n, v in zip(names, state, strict=True) if v != 0},
               "ccx_s": seconds, "cached": cached}
        if check is None:
            if reference is None:
                raise SystemExit(f"--cache-only: the rank-0 member of {model.name} is not cached")
            rows.append(row)
            continue
        ours = ours_all.normal_displacement[index]
        if reference is None:
            reference = (ours, check.normal, ours_all.displacement[index], check.skin_displacement)
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
        row["member_peak_mm"] = float(np.abs(ours).max())
        row["member_max_diff_of_peak"] = float(np.abs(check.normal - ours).max() / np.abs(ours).max())
        row["member_rms_diff_of_peak"] = float(np.sqrt(np.mean((check.normal - ours) ** 2)) / np.abs(ours).max())
        lifted = [not t.any() for t in check.touching]
        row.update(lifted=lifted, lifted_ours=[bool(r == 0) for r in ours_all.reactions[index]],
                   held_reaction_min_N=check.held_reaction_min.tolist(), free_gap_min_mm=check.free_gap_min.tolist(),
                   reaction_ccx_vs_ours_N=list(zip(check.reaction.tolist(), ours_all.reactions[index].tolist(),
                                                   strict=True)))
        # certified: no held spring pulls by more than 2 % of the largest buffer load (a contact edge) and no free
        # spring sinks below its buffer by 1e-3 mm
        row["contact_certified"] = check.certified(0.02 * max(float(ours_all.reactions[index].max()), 1.0))
        rows.append(row)
        log.info("%s %s: response diff %.2f %% of %.3f mm, certified %s, %.0f s%s", model.name, row["setting"],
                 100 * row["response_diff_of_peak"], peak, row["contact_certified"], seconds,
                 " (cached)" if cached else "")
    return rows


def print_members(rows: list[dict]) -> None:
    print("| setting | normal response peak (mm) | max diff (% of peak) | RMS diff (%) | 3D: peak (mm), max diff (%) | "
          "worst node: nearest site, from reinforcement edge (mm) | lifted (ours = ccx) | reaction ccx / ours (N) |\n"
          "|---|---|---|---|---|---|---|---|")
    for row in rows:
        certified = "certified" if row["contact_certified"] else "NOT certified"
        worst = row["worst_node"]
        print(f"| {row['setting']} | {row['response_peak_mm']:.3f} | "
              f"{100 * row['response_diff_of_peak']:.2f} | {100 * row['response_rms_diff_of_peak']:.2f} | "
              f"{row['response_3d_peak_mm']:.3f}, {100 * row['response_3d_diff_of_peak']:.2f} | "
              f"{worst['nearest_site']} {worst['nearest_site_mm']:.0f} mm, {worst['reinforcement_edge']} "
              f"{worst['from_reinforcement_edge_mm']:+.0f} | {row['lifted']} "
              f"{'=' if row['lifted'] == row['lifted_ours'] else '!='} {certified} | "
              + ", ".join(f"{a:.0f}/{b:.0f}" for a, b in row["reaction_ccx_vs_ours_N"]) + " |")


def spot(args: argparse.Namespace) -> dict:
    """The :data:`SPOT` members on every mesh of ``args.grids``; the order of each difference in h."""
    from hood_decomp.core.fe.hood_preset import LENGTH, RESOLUTIONS, build_hood_paper

    table: dict[str, list[dict]] = {}
    spacing = {}
    for grid in args.grids.split(","):
        if grid in RESOLUTIONS:
            model, (nx, _) = build_hood_paper(grid), RESOLUTIONS[grid]
        else:
            nx, ny = (int(v) for v in grid.split("x"))
            model = build_hood_paper("coarse", grid=(nx, ny))
        names = list(model.names)
        states = np.array([[setting.get(n, 0.0) for n in names] for setting in SPOT])
        table[grid] = compare(model, states, args.cache, args.lock, args.cache_only)
        spacing[grid] = LENGTH / (nx - 1)
    grids = list(table)
    h = np.array([spacing[g] for g in grids])
    measures = ("member_max_diff_of_peak", "response_diff_of_peak", "response_3d_diff_of_peak",
                "response_rms_diff_of_peak")
    order = []
    for i, setting in enumerate(SPOT):
        entry: dict[str, object] = {"setting": setting}
        for measure in measures:
            d = np.array([table[g][i].get(measure, np.nan) for g in grids])
            ok = np.flatnonzero(np.isfinite(d) & (d > 0))
            # all meshes (log-log least squares) and the two finest (the local order, nearest the asymptotic range)
            entry[measure] = (float(np.polyfit(np.log(h[ok]), np.log(d[ok]), 1)[0]) if len(ok) >= 2
                              else float("nan"))
            entry[f"{measure}_finest"] = (float(np.log(d[ok[-2]] / d[ok[-1]]) / np.log(h[ok[-2]] / h[ok[-1]]))
                                          if len(ok) >= 2 else float("nan"))
        order.append(entry)
    head = " | ".join(f"{g} (h {spacing[g]:.1f} mm)" for g in grids)
    print("| member: normal max diff, % of peak (3D %, RMS %) | " + head + " | order p, d ~ h^p (all meshes / "
          "finest two): normal, 3D | contact: lifted ours = ccx, certified |\n|---|" + "---|" * len(grids) + "---|---|")
    for i, setting in enumerate(SPOT):
        label = ", ".join(f"{n} {v:+.0f}" for n, v in setting.items()) or "rank 0 (the member itself)"
        cells, contact = [], []
        for g in grids:
            row = table[g][i]
            if "lifted" not in row:
                cells.append("not run")
                continue
            if not setting:
                cells.append(f"{100 * row['member_max_diff_of_peak']:.2f} "
                             f"(RMS {100 * row['member_rms_diff_of_peak']:.2f})")
            else:
                cells.append(f"{100 * row['response_diff_of_peak']:.2f} ({100 * row['response_3d_diff_of_peak']:.2f}, "
                             f"{100 * row['response_rms_diff_of_peak']:.2f})")
            contact.append(f"{g}: {'=' if row['lifted'] == row['lifted_ours'] else '!='}"
                           f"{'' if row['contact_certified'] else ' not certified'}")
        p = order[i]
        fit = (f"{p['member_max_diff_of_peak']:.2f} / {p['member_max_diff_of_peak_finest']:.2f}" if not setting else
               f"{p['response_diff_of_peak']:.2f} / {p['response_diff_of_peak_finest']:.2f}, "
               f"{p['response_3d_diff_of_peak']:.2f} / {p['response_3d_diff_of_peak_finest']:.2f}")
        print(f"| {label} | " + " | ".join(cells) + f" | {fit} | {'; '.join(contact)} |")
    return {"grids": grids, "spacing_mm": spacing, "members": table, "order": order}


def nonlinearity(model, count: int) -> list[dict]:
    """CalculiX NLGEOM minus linear with every buffer node held, on ``count`` members (session 4's study)."""
    from hood_decomp.core.fe.calculix import run_member_job, write_member_deck

    nonlinear = []
    names = model.names
    for state in ([0.0] * len(names), [0.0, -1.0, -1.0, 1.0, 1.0, 0.0])[:count]:
        state = np.array(state)
        fields, seconds = [], []
        for nlgeom in (False, True):
            with tempfile.TemporaryDirectory() as directory:
                deck = write_member_deck(model, state, Path(directory) / "deck.inp", buffers="held",
                                         nlgeom=nlgeom).read_text()
            start = time.perf_counter()
            fields.append(run_member_job(deck, len(model.nodes))[0])
            seconds.append(time.perf_counter() - start)
        nonlinear.append({"setting": {n: float(v) for n, v in zip(names, state, strict=True) if v != 0},
                          "linear_peak_mm": float(np.abs(fields[0]).max()),
                          "nlgeom_minus_linear_max_mm": float(np.abs(fields[1] - fields[0]).max()),
                          "linear_s": seconds[0], "nlgeom_s": seconds[1]})
        log.info("NLGEOM %s: %.4f mm of %.3f mm", nonlinear[-1]["setting"], nonlinear[-1]["nlgeom_minus_linear_max_mm"],
                 nonlinear[-1]["linear_peak_mm"])
    return nonlinear


def main() -> None:
    from hood_decomp.core.fe.calculix import run_member_job, write_member_deck
    from hood_decomp.core.fe.ensemble import factorial_plan, solve_members
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.solver import build_solver, reduce_model

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rank23", type=int, default=20, help="random rank-2/3 members")
    parser.add_argument("--nlgeom", type=int, default=2, help="members with buffers held, linear vs NLGEOM")
    parser.add_argument("--gaps", action="store_true", help="also one member with ccx GAPUNI contact (slow)")
    parser.add_argument("--spot", action="store_true", help="the SPOT members on every mesh of --grids")
    parser.add_argument("--grids", default="44x51,coarse,101x117,default",
                        help="--spot: comma-separated resolutions or NXxNY skin grids")
    parser.add_argument("--cache", type=Path, default=None, help="directory of cached CalculiX member jobs")
    parser.add_argument("--cache-only", action="store_true", help="read cached CalculiX jobs only, run none")
    parser.add_argument("--lock", type=Path, default=None,
                        help=f"flock held around each CalculiX job on a mesh of > {LOCKED_SKIN_NODES} skin nodes")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="[bench_ccx_contact %(asctime)s] %(message)s")
    OUT.mkdir(parents=True, exist_ok=True)
    if args.spot:
        path = OUT / "bench_ccx_contact_spot.json"
        path.write_text(json.dumps(spot(args), indent=2) + "\n")
        print(f"wrote {path}")
        return

    model = build_preset("hood-paper", "coarse")
    commanded, rank = factorial_plan(model.lower, model.upper)
    rng = np.random.default_rng(0)
    pick = np.concatenate([np.flatnonzero(rank <= 1),
                           rng.choice(np.flatnonzero((rank == 2) | (rank == 3)), args.rank23, replace=False)])
    rows = compare(model, commanded[pick], args.cache, args.lock, args.cache_only)
    for row, member in zip(rows, pick, strict=True):
        row.update(member=int(member), rank=int(rank[member]))
    nonlinear = nonlinearity(model, args.nlgeom)
    gaps = None
    if args.gaps:
        names = model.names
        state = np.zeros(len(names))
        state[names.index("BUFFER_L")] = 1.0
        member = solve_members(reduce_model(build_solver(model)), state[None, :])
        with tempfile.TemporaryDirectory() as directory:
            deck = write_member_deck(model, state, Path(directory) / "deck.inp", buffers="unilateral",
                                     nlgeom=True).read_text()
        start = time.perf_counter()
        u, reactions = run_member_job(deck, len(model.nodes))
        from hood_decomp.core.fe.model import patch_nodes, skin_surface

        normal = np.einsum("na,na->n", u[model.skin_nodes], skin_surface(model).normals)
        patch = patch_nodes(model, model.boundary(model.unilateral[0].boundary))
        gaps = {"setting": {"BUFFER_L": 1.0},
                "max_diff_mm": float(np.abs(normal - member.normal_displacement[0]).max()),
                "peak_mm": float(np.abs(member.normal_displacement[0]).max()),
                "reaction_ccx_N": float(sum(reactions[n][2] for n in patch)),
                "reaction_ours_N": float(member.reactions[0, 0]), "ccx_s": time.perf_counter() - start}
    result = {"resolution": "coarse", "members": rows, "nlgeom": nonlinear, "gapuni": gaps}
    path = OUT / "bench_ccx_contact.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print_members(rows)
    for entry in nonlinear:
        print(f"NLGEOM - linear, buffers held, {entry['setting']}: {entry['nlgeom_minus_linear_max_mm']:.4f} mm "
              f"(linear peak {entry['linear_peak_mm']:.3f} mm)")
    if gaps:
        print(f"GAPUNI + NLGEOM {gaps['setting']}: max diff {gaps['max_diff_mm']:.4f} mm of {gaps['peak_mm']:.3f}")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
