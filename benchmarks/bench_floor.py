"""The floor in bytes of a PCA estimate at paper scale (issue 15: "estimation at paper scale under 5 ms per field").

An estimate must at least read the arrays it combines: the field, the (K, N) basis twice (the right-hand side before
the coefficients, the reconstruction after), the one-ring incidence for the ring sums, a scan's error model and its
slide terms. This counts those bytes on a real bases file and measures this core's memory bandwidth on arrays of
those sizes, so the floor of each case is bytes / bandwidth:

- ``white``: a PCA white-noise field on every node (the brief's minimum: field, basis twice, rings, the residual and
  reconstruction written; as implemented the test also reads the 6 smooth modes, listed apart);
- ``scan``: a PCA scan at ``auto`` (a quarter of the nodes) with the every-node residual the product reports: the OLS
  reading's right-hand side over every node, the float32 slide terms over every node, the kept fit, the
  reconstruction over every node;
- ``scan-kept``: the same scan with the slide read on the kept nodes only and no every-node reconstruction or
  residual (what the estimate would cost if it reported the residual on the kept nodes alone).

Bandwidth: one BLAS thread, per array size the median over ``--repeat`` runs of a one-stream read of that many
bytes (a float64 dot of an array with itself), a copy (read + write counted) and, for a 2-D array, numpy's ``c @ A``
over the array itself (the estimate's own product) -- warm (runs in a row: the bytes in the cache where they fit, as
in a loop over one field) and cold (a ``--flush-mb`` buffer written before each run, larger than the last-level
cache, as when a node's basis waits a second between scans). Prints a table and writes
benchmarks/out/floor.json. From the repository root:
    OPENBLAS_NUM_THREADS=1 scripts/with-env python benchmarks/bench_floor.py --bases B.h5
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.method.bases import Bases  # noqa: E402
from hood_decomp.core.method.coarsening import AUTO_STRIDE  # noqa: E402
from hood_decomp.io.bases import load_bases  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "floor.json"


def log(message: str) -> None:
    print(f"[bench_floor] {message}", file=sys.stderr, flush=True)


def csr_bytes(matrix: sp.csr_matrix) -> int:
    """Bytes a sparse ring sum must read: the column indices and row pointers (an incidence needs no values)."""
    return int(matrix.indices.nbytes + matrix.indptr.nbytes)


def measured_arrays(bases: Bases) -> dict[str, np.ndarray]:
    """The arrays whose bytes make the floor, as the estimate holds them (the kept ones as copies)."""
    pca = bases.pca
    kept = bases.coarsened(AUTO_STRIDE)
    terms = bases.reading().terms
    return {"field (N,) f64": np.asarray(pca.mean_field_, float),
            "basis (K, N) f64": np.asarray(pca.components_),
            "smooth modes (N, M) f64": np.asarray(bases.residual_test().modes_),
            "one-ring column indices": bases.residual_test().rings().indices,
            "slide terms (P + K, N) f32": terms,
            "slide terms (P + K, n) f32": np.ascontiguousarray(terms[:, kept.nodes]),
            "kept basis (K, n) f64": np.asarray(kept.kept.pca.components_)}


def cases(bases: Bases) -> dict[str, list[tuple[str, int, str]]]:
    """Per case the (item, bytes, array whose bandwidth it streams at) the estimate must read or write (module
    docstring)."""
    pca = bases.pca
    k, n = pca.components_.shape
    kept = bases.coarsened(AUTO_STRIDE)
    m = kept.nodes.size
    f64, node, basis_key, kept_key = 8, "field (N,) f64", "basis (K, N) f64", "kept basis (K, n) f64"
    basis, kept_basis = k * n * f64, k * m * f64
    terms = bases.reading().terms
    rings, kept_ring = csr_bytes(bases.residual_test().rings()), csr_bytes(kept.kept.residual_test().rings())
    modes = bases.residual_test().modes_.shape[1]
    ring_key = "one-ring column indices"
    white = [("field (N,) f64", n * f64, node), ("basis (K, N) f64, right-hand side", basis, basis_key),
             ("basis (K, N) f64, reconstruction", basis, basis_key),
             ("one-ring incidence (indices, row pointers)", rings, ring_key),
             ("reconstruction and residual written (2 N f64)", 2 * n * f64, node)]
    reading = [("field (N,) f64", n * f64, node),
               ("error model: node std and correlation sums (2 N f64)", 2 * n * f64, node),
               ("basis (K, N) f64, the reading's OLS right-hand side", basis, basis_key)]
    kept_fit = [("kept basis (K, n) f64: weighted Gram and right-hand side", 2 * kept_basis, kept_key),
                (f"kept smooth and pose modes ({modes} + 6, n) f64", (modes + 6) * m * f64, kept_key),
                ("kept one-ring incidence", kept_ring, kept_key)]
    every = [(f"slide terms {terms.shape} float32, every node", terms.nbytes, "slide terms (P + K, N) f32"),
             ("node field written (N f64)", n * f64, node), ("basis (K, N) f64, reconstruction", basis, basis_key),
             ("reconstruction and residual written (2 N f64)", 2 * n * f64, node)]
    return {"white": white,
            "white, as implemented (+ the test's smooth modes)": [
                *white, (f"smooth modes (N, {modes}) f64", modes * n * f64, "smooth modes (N, M) f64")],
            "scan": reading + kept_fit + every,
            "scan-kept": reading + kept_fit + [(f"slide terms ({terms.shape[0]}, n) float32, kept nodes",
                                                terms.shape[0] * m * 4, "slide terms (P + K, n) f32")]}


def bandwidth(array: np.ndarray, repeat: int, flush: np.ndarray) -> dict[str, dict[str, float]]:
    """GB/s over ``array``'s bytes, warm (``repeat`` runs in a row) and cold (each after ``flush`` is written, which
    evicts the array from every cache level), medians: "read", a one-stream read (a dot of a float64 array of the
    same bytes with itself: the rate depends on the bytes, not on what they hold); "copy" of those bytes (read +
    write counted); "gemv", c @ A as the estimate reads a 2-D ``array`` (none for a 1-D one)."""
    stream = np.random.default_rng(0).random(array.nbytes // 8)
    target = np.empty_like(stream)
    ops = {"read": (lambda: np.dot(stream, stream), stream.nbytes),
           "copy": (lambda: np.copyto(target, stream), 2 * stream.nbytes)}
    if array.ndim == 2:
        vector = np.ones(array.shape[0], dtype=array.dtype)
        ops["gemv"] = (lambda: vector @ array, array.nbytes)
    result: dict[str, dict[str, float]] = {}
    for name, (op, nbytes) in ops.items():
        op()
        warm = []
        for _ in range(repeat):
            start = time.perf_counter()
            op()
            warm.append(time.perf_counter() - start)
        cold = []
        for _ in range(repeat):
            flush += 1.0
            start = time.perf_counter()
            op()
            cold.append(time.perf_counter() - start)
        result[name] = {"warm_gbs": nbytes / float(np.median(warm)) / 1e9,
                        "cold_gbs": nbytes / float(np.median(cold)) / 1e9,
                        "warm_ms": 1e3 * float(np.median(warm)), "cold_ms": 1e3 * float(np.median(cold))}
    result.setdefault("gemv", result["read"])  # a 1-D array is read once however it is combined
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bases", type=Path, required=True, help="a bases file (hood-decomp bases)")
    parser.add_argument("--repeat", type=int, default=41, help="runs per array, op and cache state (median)")
    parser.add_argument("--flush-mb", type=int, default=640, help="buffer written between cold runs, MB")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    bases = load_bases(args.bases)
    bases.reading().prepare()
    items = cases(bases)
    arrays = measured_arrays(bases)
    flush = np.zeros(args.flush_mb * 2**20 // 8)
    measured = {}
    for name, array in arrays.items():
        log(f"bandwidth of {name} {array.shape} ({array.nbytes / 1e6:.1f} MB)")
        measured[name] = bandwidth(array, args.repeat, flush)
    print("\n| array | MB | read warm / cold GB/s | gemv warm / cold (1-D: read) | copy warm / cold (read + write) |")
    print("|---|---:|---|---|---|")
    for name, array in arrays.items():
        m = measured[name]
        print(f"| {name} | {array.nbytes / 1e6:.1f} | " + " | ".join(
            f"{m[op]['warm_gbs']:.1f} / {m[op]['cold_gbs']:.1f}" for op in ("read", "gemv", "copy")) + " |")
    print("\nfloor: each item's bytes at its array's rate (read: a one-stream read of that many bytes; gemv: "
          "numpy's c @ A over the array)\n\n"
          "| case | MB read or written | floor at read rate, warm / cold ms | at gemv rate, warm / cold ms |\n"
          "|---|---:|---|---|")
    floors = {}
    for case, rows in items.items():
        floor = {f"{op}_{state}_ms": sum(nbytes / measured[key][op][f"{state}_gbs"] / 1e6 for _, nbytes, key in rows)
                 for op in ("read", "gemv") for state in ("warm", "cold")}
        floors[case] = {"items": rows, "bytes": sum(nbytes for _, nbytes, _ in rows), **floor}
        print(f"| {case} | {floors[case]['bytes'] / 1e6:.1f} | "
              f"{floor['read_warm_ms']:.2f} / {floor['read_cold_ms']:.2f} | "
              f"{floor['gemv_warm_ms']:.2f} / {floor['gemv_cold_ms']:.2f} |")
    for case, rows in items.items():
        print(f"\n{case}: " + "; ".join(f"{item} {nbytes / 1e6:.2f} MB" for item, nbytes, _ in rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"bandwidth": measured, "floors": floors,
                                    "shapes": {name: list(a.shape) for name, a in arrays.items()}}, indent=1))
    log(f"wrote {args.out}")


if __name__ == "__main__":
    main()
