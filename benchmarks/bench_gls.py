"""The cost of the generalised least-squares estimate at the paper's scale (issue 15: estimation under 5 ms a field).

188,700 skin nodes (a 629 x 300 grid of tests/toy_models.make_skin), a 10-component PCA basis of smooth synthetic
fields (64 members: the estimate's cost does not depend on the member count) and the contact-aware estimator on a
synthetic reduced model (4 bilateral states, 2 pads of 2 springs) of the same node count. A toy: the built-in hood's
contact-aware fit has a column per pad spring and the gate's model spread beside it, and costs far more at paper
resolution (``bench_estimate.py`` times it phase by phase: benchmarks/RESULTS.md issue 15 runs 19 P and 20 speed); this
one isolates the generalised fit and the test. A field with 20 % of the nodes unseen, timed as

- ``plain``: no error model, no skin test (what benchmarks/bench_method.py times: the paper's estimator);
- ``stated``: a white uniform stated noise with the skin's within-model test (Sigma a multiple of I: the ordinary
  fit, which is then the GLS);
- ``scan``: a scan's error model (node std 0.01-0.03 mm, correlation sums 1-4, a pose covariance of 0.03 mm markers,
  a smoothing-bias correlation of 1,000 nodes) with the skin's test: the generalised fit (Woodbury weight, the test
  made once before the fit, the sandwich);
- ``scan, no bias term``: the same without the bias correlation, where the test's one-ring part looks at the fit's
  own residual and the test is made twice (before the fit for the level, after it for the verdict);
- ``scan, ordinary``: the ``scan`` field with the weighting switched off (``fit_weight`` patched to the ordinary fit,
  as before issue 15 run 11): what the weighting itself costs is the difference to ``scan``.

Prints the best of ``--repeat`` per case, CPU and wall, and writes benchmarks/out/gls.json. Run from the repository
root (one core: ``OPENBLAS_NUM_THREADS=1``):
    scripts/with-env nice python benchmarks/bench_gls.py [--nx 629] [--ny 300] [--repeat 20]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.method.contact_estimation import ContactEstimator  # noqa: E402
from hood_decomp.core.method.estimation import estimate_pca  # noqa: E402
from hood_decomp.core.method.pca import PCABasis  # noqa: E402
from hood_decomp.core.method.residual import ResidualTest  # noqa: E402
from hood_decomp.core.types import DisplacementField, Ensemble, FieldErrorModel  # noqa: E402
from tests.toy_models import make_ensemble, make_reduced_model, make_skin, smooth_fields  # noqa: E402

OUT = ROOT / "benchmarks" / "out" / "gls.json"


def best_of(fn, repeat: int) -> tuple[float, float, object]:
    """(best wall s, best CPU s, last value) over ``repeat`` calls."""
    wall, cpu, value = np.inf, np.inf, None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        value = fn()
        wall, cpu = min(wall, time.perf_counter() - w), min(cpu, time.process_time() - c)
    return wall, cpu, value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nx", type=int, default=629)
    parser.add_argument("--ny", type=int, default=300)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    skin = make_skin(args.nx, args.ny)
    n = skin.n_nodes
    print(f"[bench_gls] {n} nodes: building the basis, the reduced model and the test", file=sys.stderr, flush=True)
    fields = smooth_fields(skin.points, 12, rng)
    states = rng.uniform(-1.0, 1.0, (64, 6))
    normal = states @ fields[:6] + 0.1 * (states**2) @ fields[6:]
    ensemble = Ensemble(model_id=skin.model_id, names=tuple(f"P{i}" for i in range(6)), n_bilateral=6,
                        lower=-np.ones(6), upper=np.ones(6), commanded=states, effective=states,
                        contact_fraction=np.zeros((64, 0)), reactions=np.zeros((64, 0)), rank=np.zeros(64, int),
                        normal_displacement=normal, displacement=np.broadcast_to(np.zeros(1), (64, n, 3)))
    pca = PCABasis(n_components=10).fit(ensemble)
    test = ResidualTest().fit(skin)
    model = make_reduced_model(skin, seed=1)
    contact = ContactEstimator().fit(model, -np.ones(6), np.ones(6), test)
    seen = skin.points[:, 0] >= np.quantile(skin.points[:, 0], 0.2)
    root = np.diag([2e-5, 2e-5, 2e-5, 0.015, 0.015, 0.015]) @ rng.normal(size=(6, 6))
    scan = FieldErrorModel("scan", rng.uniform(0.01, 0.03, n), rng.uniform(1.0, 4.0, n), 3.0, root @ root.T,
                           skin.points.mean(axis=0))
    scan_biased = dataclasses.replace(scan, bias_correlation=1000.0)
    models = {"plain": FieldErrorModel.none(), "stated": FieldErrorModel.stated(0.02, n), "scan": scan_biased,
              "scan, no bias term": scan, "scan, ordinary": scan_biased}
    truth = rng.uniform(-0.5, 0.5, 6)
    pca_values = np.where(seen, (truth @ fields[:6]) + 0.01 * rng.normal(size=n), np.nan)
    contact_values = np.where(seen, make_ensemble(model, truth[None]).normal_displacement[0]
                              + 0.01 * rng.normal(size=n), np.nan)
    results: dict = {"date": time.strftime("%Y-%m-%d"), "nodes": n, "seen": float(seen.mean()), "cases": {}}
    for case, errors in models.items():
        pca_field = DisplacementField(skin.model_id, pca_values, float(seen.mean()), float("nan"), errors)
        contact_field = DisplacementField(skin.model_id, contact_values, float(seen.mean()), float("nan"), errors)
        with_test = None if case == "plain" else test
        estimator = contact if case != "plain" else ContactEstimator().fit(model, -np.ones(6), np.ones(6))
        with contextlib.ExitStack() as stack:
            if case == "scan, ordinary":
                for module in ("estimation", "contact_estimation"):
                    stack.enter_context(mock.patch(f"hood_decomp.core.method.{module}.fit_weight",
                                                   lambda *_, **__: (None, None, None)))
            pca_wall, pca_cpu, pca_est = best_of(lambda f=pca_field, t=with_test: estimate_pca(pca, f, test=t),
                                                 args.repeat)
            c_wall, c_cpu, c_est = best_of(lambda f=contact_field, e=estimator: e.estimate(f), args.repeat)
        results["cases"][case] = {"pca_wall_ms": 1e3 * pca_wall, "pca_cpu_ms": 1e3 * pca_cpu,
                                  "pca_weighting": pca_est.weighting, "contact_wall_ms": 1e3 * c_wall,
                                  "contact_cpu_ms": 1e3 * c_cpu, "contact_weighting": c_est.weighting}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(results, indent=1))
    print(f"{'field':<20} {'PCA ms (wall / CPU)':>22} {'weighting':>12} {'contact ms (wall / CPU)':>26} "
          f"{'weighting':>12}")
    for case, row in results["cases"].items():
        print(f"{case:<20} {row['pca_wall_ms']:>10.2f} / {row['pca_cpu_ms']:<9.2f} {row['pca_weighting']:>12} "
              f"{row['contact_wall_ms']:>12.2f} / {row['contact_cpu_ms']:<11.2f} {row['contact_weighting']:>12}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
