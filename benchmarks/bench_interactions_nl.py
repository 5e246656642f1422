"""Benchmark: interaction effects and Fig. 11 on the geometrically nonlinear hood-paper (issue 21).

Input: a nonlinear ensemble store written by ``hood-decomp ensemble --nonlinear --range HINGE_Y=-0.5:0.5`` (built
here into ``--store`` when that file does not exist: about 140 s coarse on an idle machine).
1. Every rank-2 member: its factorial interaction's peak, its distance from its own effects' span (LOADS and its two
   single effects: what decomposition step 3 leaves) and from the whole rank-0/1 span (what the paper's Fig. 5
   measures), normal and 3D; the hierarchical basis at 0.1 and 0.05 mm with both ``span`` settings.
2. Fig. 11: fields of new full nonlinear solves (``NonlinearSolver``, not the reduced model) with LOCK_L and LOCK_R
   moved (at the grid's corner, at Fig. 11's 0.8 / -0.7, and Fig. 11's full setting with the hinges), PCA estimate,
   decomposition; the LOCK_L & LOCK_R effect's partial displacement against the planted interaction
   |u(a_L + a_R) - u(a_L) - u(a_R) + u0| (3D, four full solves with the other parameters as in the field).

Usage: scripts/with-env python benchmarks/bench_interactions_nl.py [--resolution coarse] [--store PATH]
Prints tables and writes benchmarks/out/bench_interactions_nl_<resolution>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "out"
CASES = {
    "corner (LOCK_L 1, LOCK_R -1)": {"LOCK_L": 1.0, "LOCK_R": -1.0},
    "locks (LOCK_L 0.8, LOCK_R -0.7)": {"LOCK_L": 0.8, "LOCK_R": -0.7},
    "Fig. 11 (HINGE_X 0.4, HINGE_Y -0.3, LOCK_L 0.8, LOCK_R -0.7)":
        {"HINGE_X": 0.4, "HINGE_Y": -0.3, "LOCK_L": 0.8, "LOCK_R": -0.7},
}
PAIR = ("LOCK_L", "LOCK_R")


def rank2_distances(ensemble) -> list[dict[str, object]]:
    """Per rank-2 member: factorial interaction peak, distance from its own and from the whole rank-0/1 span (mm)."""
    names, x = ensemble.names, np.asarray(ensemble.normal_displacement, dtype=float)
    x3 = np.asarray(ensemble.displacement, dtype=float)
    index = {tuple(row.tolist()): m for m, row in enumerate(ensemble.commanded)}
    origin = index[(0.0,) * len(names)]

    def single(p: int, value: float) -> int:
        state = [0.0] * len(names)
        state[p] = value
        return index[tuple(state)]

    def span(params) -> list[int]:
        return [single(p, v) for p in params for v in (ensemble.upper[p], ensemble.lower[p])]

    def distance(data: np.ndarray, members: list[int], target: int) -> np.ndarray:
        q = np.linalg.qr(np.array([data[origin].ravel()] + [(data[m] - data[origin]).ravel() for m in members]).T)[0]
        rest = data[target].ravel() - q @ (q.T @ data[target].ravel())
        return rest.reshape(data[target].shape)

    rows = []
    everything = span(range(len(names)))
    for m in np.flatnonzero(ensemble.rank == 2):
        i, j = np.flatnonzero(ensemble.commanded[m])
        a, b = ensemble.commanded[m, i], ensemble.commanded[m, j]
        interaction = x[m] - x[single(i, a)] - x[single(j, b)] + x[origin]
        rows.append({
            "member": f"{names[i]}{'+' if a > 0 else '-'} & {names[j]}{'+' if b > 0 else '-'}",
            "interaction_peak_mm": float(np.abs(interaction).max()),
            "own_span_mm": float(np.abs(distance(x, span((i, j)), m)).max()),
            "whole_span_mm": float(np.abs(distance(x, everything, m)).max()),
            "whole_span_3d_mm": float(np.linalg.norm(distance(x3, everything, m), axis=1).max()),
        })
    return sorted(rows, key=lambda r: -r["own_span_mm"])


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=["coarse", "default"], default="coarse")
    parser.add_argument("--store", type=Path, default=None, help="nonlinear ensemble store (built if missing)")
    args = parser.parse_args()

    from hood_decomp.core.fe.geometric import NonlinearSolver
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.core.fe.solver import build_solver
    from hood_decomp.core.method.bases import build_bases, decompose_field, estimate_field
    from hood_decomp.core.method.hierarchical import SPANS, HierarchicalBasis
    from hood_decomp.core.types import DisplacementField
    from hood_decomp.io.ensemble_store import load_ensemble, load_skin

    out: dict[str, object] = {"resolution": args.resolution, "load_start": os.getloadavg()}
    scratch = tempfile.TemporaryDirectory()
    store = args.store or Path(scratch.name) / "ensemble.h5"
    if not store.exists():
        model_dir = Path(scratch.name) / "model"
        cli = [sys.executable, "-m", "hood_decomp.cli"]
        subprocess.run([*cli, "model", "--preset", "hood-paper", "--resolution", args.resolution, "--out",
                        str(model_dir)], check=True)
        start = time.perf_counter()
        subprocess.run([*cli, "ensemble", "--model", str(model_dir), "--out", str(store), "--nonlinear", "--range",
                        "HINGE_Y=-0.5:0.5"], check=True)
        out["ensemble_s"] = time.perf_counter() - start
    ensemble, skin = load_ensemble(store), load_skin(store)
    out["rank2"] = rank2_distances(ensemble)
    print("| rank-2 member | factorial interaction | from its own effects' span | from the whole span | whole, 3D |")
    print("|---|---:|---:|---:|---:|")
    for row in out["rank2"][:12]:
        print(f"| {row['member']} | {row['interaction_peak_mm']:.3f} | {row['own_span_mm']:.3f} | "
              f"{row['whole_span_mm']:.3f} | {row['whole_span_3d_mm']:.3f} |")
    for span in SPANS:
        for epsilon in (0.1, 0.05):
            basis = HierarchicalBasis(epsilon, span).fit(ensemble)
            out[f"effects_{span}_{epsilon}"] = list(basis.effect_names_)
            print(f"span {span}, epsilon {epsilon} mm: {len(basis.effect_names_)} effects: "
                  f"{', '.join(basis.effect_names_)}")

    model = build_preset("hood-paper", args.resolution)
    names = list(model.names)
    full = NonlinearSolver(build_solver(model))
    fig11 = {}
    print("| span | field | effects after coarsening (share) | LOCK_L & LOCK_R partial peak | planted peak | "
          "max difference | reconstruction RMS |\n|---|---|---|---:|---:|---:|---:|")
    for span in SPANS:
        bases = build_bases(ensemble, skin, None, 10, None, 0.1, span)
        for case, setting in CASES.items():
            state = np.array([setting.get(n, 0.0) for n in names])
            faces = np.array([state, state, state, state])
            faces[1, names.index(PAIR[1])] = faces[2, names.index(PAIR[0])] = 0.0
            faces[3, [names.index(p) for p in PAIR]] = 0.0
            members = full.members(faces)
            u = members.displacement
            planted = np.linalg.norm(u[0] - u[1] - u[2] + u[3], axis=1)
            field = DisplacementField(bases.model_id, members.normal_displacement[0], 1.0, float("nan"))
            estimate = estimate_field(bases, field, method="pca")
            decomposition = decompose_field(bases, field, estimate)
            effects = {e.name: e for e in decomposition.effects}
            pair = effects.get(" & ".join(PAIR))
            row = {"effects": [[e.name, e.share] for e in decomposition.effects],
                   "pca_estimate_mm": estimate.values.tolist(), "planted_peak_mm": float(planted.max()),
                   "partial_peak_mm": None if pair is None else float(pair.partial_displacement.max()),
                   "max_difference_mm": None if pair is None else
                   float(np.abs(pair.partial_displacement - planted).max()),
                   "reconstruction_rms_mm": float(decomposition.reconstruction_rms)}
            fig11[f"{span}: {case}"] = row
            shares = ", ".join(f"{n} {100 * s:.1f} %" for n, s in row["effects"])
            print(f"| {span} | {case} | {shares} | {_mm(row['partial_peak_mm'])} | {row['planted_peak_mm']:.4f} | "
                  f"{_mm(row['max_difference_mm'])} | {row['reconstruction_rms_mm']:.4f} |")
    out["fig11"] = fig11
    out["load_end"] = os.getloadavg()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"bench_interactions_nl_{args.resolution}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
