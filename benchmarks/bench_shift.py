"""A shift of parts (issue 20): throughput on Dask, SPC alarm delays and false-alarm rates over seeds, recurring
residuals at default resolution. One command:

    scripts/with-env python benchmarks/bench_shift.py [--fields 100] [--bags 12] [--seeds 5] [--recurring 300]
        [--feed 100] [--only spc|throughput|recurring|feed]

1. **SPC over seeds** (20 x 20 hood, every part through generator -> field -> contact-aware estimate): false-alarm
   rate per rule and boundary on stable shifts of 1,000 parts (limits from the first 200), and the delay of the first
   alarm after a 3-spread step (HINGE_Y) and a 0.5-spread-per-10-parts drift (LOCK_L), per seed.
2. **Throughput** (default hood, 30,107 skin nodes): parts/s with 1 and 2 local Dask workers and the workers' peak
   memory, from fields (.vtu) and from bags of 500,000-point single-view scans (scan -> registered field -> estimate
   -> correction -> decomposition -> within-model test, the nodes' path); a 16-worker extrapolation from the
   measured per-part cost.
3. **Recurring residuals at default resolution**: a shift with hinge_R.z in 10 % and a 0.1-0.2 mm bump near BUFFER_L
   in 15 % of the parts: the candidate named with its magnitudes, the bump offered as a measured effect with the
   cross-validated residual RMS against 1.5 x the error model's and the declared-parameter errors after; a shift
   without undeclared effect: nothing offered.
4. **Feed ceiling** (`--only feed --feed 100`): the parts/s one client can feed from a bag of 500k-point clouds when
   the workers do nothing with them (the product's run_batch with a bases path that does not exist): the bound on
   any worker count for bag input.
Prints tables and writes benchmarks/out/bench_shift.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import pathlib
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.fe.ensemble import factorial_plan, simulate_ensemble  # noqa: E402
from hood_decomp.core.fe.hood_preset import build_hood  # noqa: E402
from hood_decomp.core.fe.model import skin_surface  # noqa: E402
from hood_decomp.core.fe.solver import build_solver, reduce_model  # noqa: E402
from hood_decomp.core.loop.candidates import augment_reduced, candidate_fields, enumerate_candidates, motion  # noqa: E402
from hood_decomp.core.loop.measured_effects import analyse_recurring  # noqa: E402
from hood_decomp.core.method.bases import analyse_estimate, build_bases, estimate_field  # noqa: E402
from hood_decomp.core.types import DisplacementField  # noqa: E402
from hood_decomp.io.bases import save_bases  # noqa: E402
from hood_decomp.io.fields import write_field  # noqa: E402
from hood_decomp.io.history import History  # noqa: E402
from hood_decomp.io.json_values import json_ready  # noqa: E402
from hood_decomp.shift.part import Options  # noqa: E402
from hood_decomp.shift.runner import _peak_rss_mb, dask_client, run_batch, worker_peak_memory_mb  # noqa: E402
from hood_decomp.shift.sources import find_sources, iter_tasks  # noqa: E402
from hood_decomp.shift.spc import RULES, individuals_chart  # noqa: E402
from hood_decomp.synthetic.shift import ProcessModel, bump_field, make_part, plan_shift  # noqa: E402

OUT = ROOT / "benchmarks" / "out"


class Hood:
    """A hood at one resolution with its bases and a truth model holding hinge_R.z."""

    def __init__(self, resolution: str, grid: tuple[int, int] | None = None) -> None:
        start = time.perf_counter()
        self.model = build_hood(resolution, grid=grid)
        self.skin = skin_surface(self.model)
        self.solver = build_solver(self.model)
        self.reduced = reduce_model(self.solver)
        self.candidates = candidate_fields(self.solver, enumerate_candidates(self.model))
        self.truth = augment_reduced(self.reduced, candidate_fields(self.solver, [motion("hinge_R", "z")]),
                                     ["hinge_R.z"])
        commanded, rank = factorial_plan(self.model.lower, self.model.upper)
        ensemble = simulate_ensemble(self.reduced, commanded, rank, self.model.lower, self.model.upper)
        self.bases = build_bases(ensemble, self.skin, self.reduced)
        print(f"hood {resolution} {grid or ''}: {self.skin.n_nodes} skin nodes, set up in "
              f"{time.perf_counter() - start:.0f} s", file=sys.stderr)


def spc_over_seeds(seeds: int) -> dict:
    hood = Hood("coarse", (20, 20))
    names = hood.reduced.names

    def values(process: ProcessModel, n: int, seed: int) -> np.ndarray:
        plan = plan_shift(names, process, n, seed=seed)
        return np.array([estimate_field(hood.bases, make_part(plan, i, hood.truth, hood.skin).field).values
                         for i in range(n)])

    rates = {name: {rule: [] for rule in RULES} for name in names}
    above = []  # (rule, boundary, seed, rate, baseline sigma estimate / sigma of the 800 monitored parts)
    for seed in range(seeds):
        stable = values(ProcessModel(drift_label=None, step_label=None), 1000, 100 + seed)
        for column, name in enumerate(names):
            chart = individuals_chart(name, stable[:, column], 200)
            for rule in RULES:
                rates[name][rule].append(chart.alarms[rule].size / 800)
                if chart.alarms[rule].size > 8:
                    above.append((rule, name, seed, chart.alarms[rule].size / 800,
                                  chart.sigma_estimate / float(np.std(stable[200:, column], ddof=1))))
        print(f"spc: stable seed {seed} done", file=sys.stderr)
    step_delay, drift_delay = [], []
    for seed in range(4 * seeds):
        shifted = values(ProcessModel(drift_start=220, step_start=220), 260, 200 + seed)
        step = individuals_chart("HINGE_Y", shifted[:, names.index("HINGE_Y")], 200).first_alarm(220)
        drift = individuals_chart("LOCK_L", shifted[:, names.index("LOCK_L")], 200).first_alarm(220)
        step_delay.append(np.inf if step is None else step[0] - 220)
        drift_delay.append(np.inf if drift is None else drift[0] - 220)
    worst = {rule: max(max(rates[n][rule]) for n in names) for rule in RULES}
    mean = {rule: float(np.mean([np.mean(rates[n][rule]) for n in names])) for rule in RULES}
    print("\nSPC on the 20 x 20 hood, limits from 200 parts, 800 monitored parts per stable shift")
    pairs = len(names) * seeds
    print(f"{'rule':<16}{'mean rate':>10}{'worst (boundary, seed)':>24}{'pairs above 1 %':>17}")
    for rule in RULES:
        print(f"{rule:<16}{100 * mean[rule]:>9.2f}%{100 * worst[rule]:>23.2f}%"
              f"{sum(a[0] == rule for a in above):>10d} / {pairs}")
    for rule, name, seed, rate, ratio in above:
        print(f"  above 1 %: {rule} {name} seed {seed}: {100 * rate:.2f} %, baseline sigma / monitored sigma "
              f"{ratio:.3f}")
    step_delay, drift_delay = np.array(step_delay), np.array(drift_delay)
    print(f"step 3 spreads: alarm delay median {np.median(step_delay):.0f}, max {step_delay.max():.0f} parts, "
          f"within 10 parts in {100 * np.mean(step_delay < 10):.0f} % of {step_delay.size} seeds")
    print(f"drift 0.5 spread / 10 parts: delay median {np.median(drift_delay):.0f}, max {drift_delay.max():.0f}, "
          f"within 30 parts in {100 * np.mean(drift_delay < 30):.0f} % of {drift_delay.size} seeds")
    return {"rates_per_boundary": rates, "mean_rate": mean, "worst_rate": worst, "above_1_percent": above,
            "load_average": os.getloadavg(), "step_delay": step_delay,
            "drift_delay": drift_delay, "seeds_stable": seeds, "seeds_shifted": 4 * seeds}


def _bags(hood: Hood, directory: pathlib.Path, n: int) -> None:
    """The first n parts of the fields' shift (same plan and seed), scanned (500k points) into one bag, each scan
    written as it is made: memory of one scan, not of n (write_scenario_bag consumes the generator lazily)."""
    from hood_decomp.ros.scan_bag import write_scenario_bag
    from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan
    from hood_decomp.synthetic.scenarios import ScenarioScan

    config = ScannerConfig(n_points=500_000, noise_mm=0.02)
    plan = plan_shift(hood.reduced.names, ProcessModel(drift_label=None, step_label=None), n, seed=3)
    start = time.perf_counter()

    def scans() -> Iterator[ScenarioScan]:
        for i in range(n):
            part = make_part(plan, i, hood.truth, hood.skin)
            truth = dict(zip(hood.reduced.names, (float(v) for v in part.truth), strict=True))
            yield ScenarioScan(part.part_id, truth, truth, {}, {}, part.clean,
                               synthesize_scan(hood.skin, part.displacement, config, seed=i), config)
            if (i + 1) % 10 == 0 or i + 1 == n:
                elapsed = time.perf_counter() - start
                print(f"bags: scan {i + 1}/{n}, {elapsed / (i + 1):.2f} s each, peak RSS "
                      f"{_peak_rss_mb():.0f} MB, load {os.getloadavg()[0]:.1f}", file=sys.stderr)

    write_scenario_bag(directory / "shift", scans(), model_id=hood.skin.model_id, resolution="default",
                       description="bench_shift parts")


def throughput(n_fields: int, n_bags: int) -> dict:
    hood = Hood("default")
    work = pathlib.Path(tempfile.mkdtemp(prefix="bench_shift_"))
    save_bases(work / "bases.h5", hood.bases)
    plan = plan_shift(hood.reduced.names, ProcessModel(drift_label=None, step_label=None), max(n_fields, 1), seed=3)
    (work / "fields").mkdir()
    for i in range(n_fields):
        part = make_part(plan, i, hood.truth, hood.skin)
        write_field(work / "fields" / f"{part.part_id}.vtu", hood.skin, part.field)
        if (i + 1) % 100 == 0:
            print(f"fields: {i + 1}/{n_fields}", file=sys.stderr)
    (work / "bags").mkdir()
    writing = {}
    if n_bags:
        rss_before, start = _peak_rss_mb(), time.perf_counter()
        _bags(hood, work / "bags", n_bags)
        writing = {"parts": n_bags, "seconds": time.perf_counter() - start, "peak_rss_mb_before": rss_before,
                   "peak_rss_mb_after": _peak_rss_mb(),
                   "bag_bytes": sum(f.stat().st_size for f in (work / "bags").rglob("*") if f.is_file()),
                   "load_average_1min": os.getloadavg()[0]}
        print(f"bag written: {writing['bag_bytes'] / 1e9:.1f} GB in {writing['seconds']:.0f} s, peak RSS of the "
              f"writer {rss_before:.0f} -> {writing['peak_rss_mb_after']:.0f} MB", file=sys.stderr)
    rows = []
    for kind, directory, count in (("fields", work / "fields", n_fields), ("bags", work / "bags", n_bags)):
        if count == 0:  # --fields 0 or --bags 0: that input not measured in this run
            continue
        sources = find_sources([directory])
        for workers in (1, 2):
            load_before = os.getloadavg()[0]
            with dask_client(None, workers) as client:
                with History(work / f"{kind}_{workers}.sqlite") as history:
                    # the first part of each worker loads the bases and prepares the estimators: timed apart
                    summary = run_batch(client, iter_tasks(sources), count, str(work / "bases.h5"), history,
                                        Options())
                memory = worker_peak_memory_mb(client)
            per_part = workers / summary.rate
            rows.append({"input": kind, "workers": workers, "parts": count, "seconds": summary.seconds,
                         "parts_per_s": summary.rate, "seconds_per_part_per_worker": per_part,
                         "failed": len(summary.failed), "peak_memory_mb_per_worker": max(memory.values()),
                         "extrapolated_16_workers_parts_per_s": 16 / per_part,
                         "extrapolated_1000_parts_16_workers_s": 1000 * per_part / 16,
                         "load_average_1min": [load_before, os.getloadavg()[0]]})
            print(f"throughput: {kind} x {count}, {workers} workers: {summary.rate:.2f} parts/s", file=sys.stderr)
    print("\nThroughput, default hood (30,107 skin nodes), local Dask cluster on this 2-core machine")
    print(f"{'input':<8}{'workers':>8}{'parts':>7}{'parts/s':>9}{'s/part/worker':>15}{'peak MB/worker':>16}"
          f"{'16 workers: parts/s':>21}{'load':>12}")
    for r in rows:
        print(f"{r['input']:<8}{r['workers']:>8}{r['parts']:>7}{r['parts_per_s']:>9.2f}"
              f"{r['seconds_per_part_per_worker']:>15.2f}{r['peak_memory_mb_per_worker']:>16.0f}"
              f"{r['extrapolated_16_workers_parts_per_s']:>21.1f}"
              f"{r['load_average_1min'][0]:>6.1f}-{r['load_average_1min'][1]:.1f}")
    shutil.rmtree(work, ignore_errors=True)
    return {"rows": rows, "load_average": os.getloadavg(), "bag_writing": writing}


def feed_ceiling(n: int) -> dict:
    """What one client (with the LocalCluster's scheduler in its process) can feed: n 500k-point clouds from a bag
    through the product's run_batch (read, submit, ship to a worker, record in the history) with a bases path that
    does not exist, so each worker's part fails at once after receiving its cloud. Parts/s here bound any worker
    count from above for bag input; the clouds are random points (the work is skipped, only the bytes matter)."""
    from hood_decomp.ros.scan_bag import write_scenario_bag
    from hood_decomp.synthetic.scanner import ScannerConfig, SyntheticScan
    from hood_decomp.synthetic.scenarios import ScenarioScan

    work = pathlib.Path(tempfile.mkdtemp(prefix="bench_shift_feed_"))
    rng = np.random.default_rng(0)
    config = ScannerConfig(n_points=500_000)

    def scans() -> Iterator[ScenarioScan]:
        for i in range(n):
            scan = SyntheticScan(rng.uniform(-1000, 1000, (500_000, 3)), np.eye(4), np.zeros((0, 3)),
                                 np.zeros(0, np.int64), np.zeros((0, 3)), np.eye(4), np.eye(4), 0.02, 500_000, 0)
            yield ScenarioScan(f"p{i}", {}, {}, {}, {}, np.zeros(0), scan, config)

    write_scenario_bag(work / "bags" / "feed", scans(), model_id="random", resolution="none", description="feed")
    sources = find_sources([work / "bags"])
    rows = []
    for workers in (1, 2):
        load_before = os.getloadavg()[0]
        with dask_client(None, workers) as client, History(work / f"feed_{workers}.sqlite") as history:
            summary = run_batch(client, iter_tasks(sources), n, str(work / "no_bases.h5"), history, Options())
        assert len(summary.failed) == n, "every part must fail at its bases (nothing else measured)"
        rows.append({"workers": workers, "parts": n, "seconds": summary.seconds, "parts_per_s": summary.rate,
                     "mb_per_s": summary.rate * 500_000 * 16 / 1e6,
                     "load_average_1min": [load_before, os.getloadavg()[0]]})
        print(f"feed ceiling, {workers} workers: {summary.rate:.1f} parts/s "
              f"({rows[-1]['mb_per_s']:.0f} MB/s of clouds), load {load_before:.1f}", file=sys.stderr)
    shutil.rmtree(work, ignore_errors=True)
    return {"rows": rows}


def recurring(n: int) -> dict:
    hood = Hood("default")
    results = {}
    for label, shares in (("with_effects", (0.1, 0.15)), ("without", (0.0, 0.0))):
        process = ProcessModel(candidate_share=shares[0], bump_share=shares[1], drift_label=None, step_label=None)
        plan = plan_shift(hood.reduced.names, process, n, seed=21)
        parts = [make_part(plan, i, hood.truth, hood.skin) for i in range(n)]
        estimates = [estimate_field(hood.bases, p.field) for p in parts]
        outside = np.array([not analyse_estimate(hood.bases, e, 0.02, 0.01).within_model for e in estimates])
        values = np.array([e.values for e in estimates])
        rows = np.flatnonzero(outside)
        found = analyse_recurring(hood.bases, np.array([estimates[i].residual for i in rows]),
                                  np.full(rows.size, 0.02), values[rows], np.median(values[~outside], axis=0),
                                  hood.candidates)
        entry = {"parts": n, "outside": int(rows.size), "message": found.message, "modes": []}
        bump = bump_field(hood.skin, process.bump_center, process.bump_radius_mm)
        for mode in found.modes:
            carrying = rows[mode.parts]
            info = {"name": mode.name, "kind": mode.kind, "parts": int(carrying.size),
                    "true_effects": {k: int(sum(plan.effect_of(i) == k for i in carrying))
                                     for k in ("none", "candidate", "bump")},
                    "rms_before_mm": mode.rms_before, "rms_after_mm": mode.rms_after,
                    "expected_rms_mm": mode.expected_rms,
                    "rms_after_over_expected_max": float(np.max(mode.rms_after / mode.expected_rms))
                    if mode.rms_after.size else None}
            if mode.kind == "candidate":
                # parts whose true effect is another one are counted in true_effects; z over the candidate's parts
                mine = np.array([plan.effect_of(i) == "candidate" for i in carrying])
                z = ((mode.amplitude[mode.parts] - plan.amplitude[carrying]) / mode.std[mode.parts])[mine]
                info.update(z_abs_max=float(np.max(np.abs(z))), within_3_std=float(np.mean(np.abs(z) <= 3)),
                            mean_amplitude=float(np.mean(mode.amplitude[mode.parts][mine])),
                            mean_truth=float(np.mean(plan.amplitude[carrying][mine])))
            else:
                without = np.array([estimate_field(hood.bases, DisplacementField(
                    hood.skin.model_id, parts[i].field.normal_displacement - plan.amplitude[i] * bump, 1.0,
                    0.02)).values for i in carrying])
                after = np.abs(mode.values_after[mode.parts] - without).max(axis=1)
                before = np.abs(values[carrying] - without).max(axis=1)
                truth_after = np.abs(mode.values_after[mode.parts] - plan.truth[carrying]).max(axis=1)
                truth_without = np.abs(without - plan.truth[carrying]).max(axis=1)
                info.update(cos_to_bump=float(mode.field @ bump / np.linalg.norm(mode.field) / np.linalg.norm(bump)),
                            declared_error_before_max=float(before.max()),
                            declared_error_after_max=float(after.max()),
                            declared_error_after_median=float(np.median(after)),
                            error_to_truth_after_max=float(truth_after.max()),
                            error_to_truth_without_bump_max=float(truth_without.max()))
            entry["modes"].append(info)
        results[label] = entry
        print(f"\nrecurring residuals, default hood, {label}: {n} parts, {rows.size} outside the model: "
              f"{found.message}")
        for info in entry["modes"]:
            print("  " + json.dumps(json_ready({k: v for k, v in info.items() if not isinstance(v, np.ndarray)})))
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fields", type=int, default=100, help="parts given as fields (default 100)")
    parser.add_argument("--bags", type=int, default=12, help="parts given as 500k-point scans in a bag (default 12)")
    parser.add_argument("--seeds", type=int, default=5, help="stable shifts for the false-alarm rates (default 5)")
    parser.add_argument("--recurring", type=int, default=300, help="parts of the recurring-residual shifts")
    parser.add_argument("--feed", type=int, default=100, help="random 500k-point clouds for the client's feed ceiling")
    parser.add_argument("--only", choices=("spc", "throughput", "recurring", "feed"), default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "bench_shift.json"
    result = json.loads(path.read_text()) if path.exists() and args.only else {}
    result.update({"date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count()})
    if args.only in (None, "spc"):
        result["spc"] = spc_over_seeds(args.seeds)
    if args.only in (None, "recurring"):
        result["recurring"] = recurring(args.recurring)
    if args.only in (None, "feed"):
        result["feed_ceiling"] = feed_ceiling(args.feed)
    if args.only in (None, "throughput"):
        measured = throughput(args.fields, args.bags)
        # rows of other (input, parts) from earlier runs are kept: a 1,000-field run and a bag run may be separate
        kept = [row for row in result.get("throughput", {}).get("rows", [])
                if (row["input"], row["parts"]) not in {(r["input"], r["parts"]) for r in measured["rows"]}]
        result["throughput"] = {**measured, "rows": kept + measured["rows"]}
    path.write_text(json.dumps(json_ready(result), indent=2) + "\n")
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
