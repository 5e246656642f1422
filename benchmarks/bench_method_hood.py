"""Section 4.1's validation on the built-in hood at default resolution: 729 training members, 1400 random validation
members, truth from the embedded FE solver with exact pad contact (tests/hood_validation.py, the code the tests run on
a subset of the same members).

Run: scripts/with-env python benchmarks/bench_method_hood.py [--resolution default] [--members 1400]
Writes Fig. 8/9/10-style PNGs and summary.json to benchmarks/out/method_validation/ and prints the table of
RESULTS.md "Real hood, default resolution" (max |error| per parameter, all members and observable states only).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.method.decomposition import reconstruct_members  # noqa: E402
from hood_decomp.core.method.hierarchical import HierarchicalBasis  # noqa: E402
from hood_decomp.plots.method import (  # noqa: E402
    plot_error_boxplot,
    plot_error_histogram,
    plot_explained_variance,
)
from tests.hood_validation import build, run_validation, validation_members  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "method_validation"
logger = logging.getLogger("bench_method_hood")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=("coarse", "default"), default="default")
    parser.add_argument("--members", type=int, default=1400, help="random validation members")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    start = time.perf_counter()
    model, skin, reduced, training = build(args.resolution)
    logger.info("%s hood and its %d training members in %.0f s", args.resolution, training.n_members,
                time.perf_counter() - start)
    validation = validation_members(model, reduced, args.members)
    logger.info("%d validation members solved at %.0f s", args.members, time.perf_counter() - start)
    pca, result = run_validation(skin, reduced, training, validation, model)
    logger.info("estimated at %.0f s", time.perf_counter() - start)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    names = list(model.names)
    plot_explained_variance(pca.explained_variance_ratio_, out / "fig8_explained_variance.png")
    for key in ("pca", "contact", "contact_noisy"):
        plot_error_boxplot(names, result[key], out / f"fig9_{key}.png",
                           f"estimation error ({key}), {args.members} members")
    z = np.abs(result["contact_noisy"] / result["noisy_std"])
    summary = {"resolution": args.resolution, "skin_nodes": skin.n_nodes,
               "noisy_max_z_flag_right": float(z[result["noisy_flag_ok"]].max()),
               "noisy_fraction_z_above_3_flag_right": float(np.mean(z[result["noisy_flag_ok"]] > 3.0)),
               "noisy_flag_wrong_pads": int((~result["noisy_flag_ok"]).sum()),
               "noisy_median_std_mm": dict(zip(names, np.median(result["noisy_std"], axis=0).tolist(), strict=True)),
               "members": validation.n_members, "n_pad_springs": int(reduced.k.size),
               "contact_seconds_mean": float(np.mean(result["seconds"])),
               "lifted_wrong": result["lifted_wrong"], "commanded_above_reported_mm": result["commanded_above"],
               "pca_notes": list(pca.notes_)}
    rows = []
    for key in ("pca", "contact", "contact_noisy"):
        largest = np.abs(result[key]).max(axis=0)
        observable = np.where(result["observable"], np.abs(result[key]), 0.0).max(axis=0)
        summary[f"{key}_max_abs_mm"] = dict(zip(names, largest.tolist(), strict=True))
        summary[f"{key}_max_abs_observable_mm"] = dict(zip(names, observable.tolist(), strict=True))
        rows += [(key, largest), (f"{key}, observable", observable)]
    rows.append(("median stated std (noisy)", np.median(result["noisy_std"], axis=0)))
    for epsilon in (0.1, 0.01):
        begin = time.perf_counter()
        basis = HierarchicalBasis(epsilon=epsilon).fit(training)
        seconds = time.perf_counter() - begin
        worst = np.abs(reconstruct_members(basis, validation.normal_displacement)
                       - validation.normal_displacement).max(axis=1)
        plot_error_histogram(worst, out / f"fig10_eps{epsilon}.png",
                             f"max reconstruction error, epsilon {epsilon} mm, {len(basis.effect_names_)} effects")
        summary[f"hierarchical_eps{epsilon}"] = {"effects": list(basis.effect_names_), "seconds": seconds,
                                                 "validation_max_error_mm": float(worst.max()),
                                                 "validation_median_max_error_mm": float(np.median(worst))}
    summary["seconds"] = time.perf_counter() - start
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"max |error| (mm), {args.resolution} hood, {args.members} members")
    print(f"{'estimator':<28}" + "".join(f"{n:>11}" for n in names))
    for label, values in rows:
        print(f"{label:<28}" + "".join(f"{v:11.2e}" for v in values))
    print(f"lifted flags wrong (noise-free): {result['lifted_wrong']}; wrong noisy pad flags: "
          f"{summary['noisy_flag_wrong_pads']}; z > 3 where the flag is right: "
          f"{summary['noisy_fraction_z_above_3_flag_right']:.4f}")
    print(f"wrote {out / 'summary.json'} and the figures in {summary['seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
