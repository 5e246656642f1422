"""Scan -> displacement field, like with like against CloudCompare's cloud-to-mesh distance, in one run.

Per resolution (the hood preset's skin at default and paper resolution) one synthetic structured-light scan of the
displaced skin (0.05 mm range noise, fixture background, outliers) is taken with about 10 million points in the part
frame; the 100k, 1M and 5M clouds are sorted random subsets of it (the same view, sparser). Every cloud is one PLY
file; the nominal skin is one mesh PLY. On the same files:

- CloudCompare C2M (``-C2M_DIST``) with ``-MAX_DIST 5`` (hood_decomp's own 5 mm cap) and without it, as a fresh
  process under ``/usr/bin/time -v`` (wall, peak RSS), loading and saving included;
- hood_decomp file to file: ``hood-decomp estimate --bases B --scan cloud.ply`` as a fresh process under
  ``/usr/bin/time -v`` (start-up, bases and prepared skin load, PLY read, field, estimate);
- hood_decomp per scan: ``field_from_scan`` (marker registration included) in a child process with the prepared
  skin read from the bases file: first call, median of the repeats, peak RSS of the scan step (VmHWM reset before
  it) and the field's RMS error against the truth on seen nodes.
- hood_decomp cold run by phase: the same work as ``estimate --scan`` in a fresh process, timed per phase (imports,
  bases load, prepared skin, PLY read, scan path with registration, estimate, JSON write; wall and CPU s), median
  of the repeats: where a one-off run's time goes.
Both hood_decomp runs accept any coverage (``min_coverage`` 0): 100k points cannot cover 188k paper nodes (the
coverage is reported).

The bases files carry a toy reduced model on the real skin (tests/toy_models.py: 3 parameters, 27 members): a
paper-resolution FE ensemble needs about 9.5 GB, which this shared machine cannot spare; the scan step, the file
reading and the prepared skin, which are what is measured, are those of the real skin. The time per scan is fitted
as a + b * points over the sizes from 1M on (a: the per-node work); the marginal cost per point at 1M is the slope
between the two smallest of those sizes, at the top the slope between the two largest (so 1M, 2M, ..., 5M, 10M
gives 1M->2M against 5M->10M), and their ratio is checked against 1.15; the scan step's peak memory at the largest
size against 1 GB. The load average is recorded with every figure.

Prints a table and writes benchmarks/out/bench_scan.json. Run from the repository root inside the environment:
    scripts/with-env python benchmarks/bench_scan.py [--repeats 5] [--uncapped-repeats 3]
        [--sizes 1e5,1e6,2e6,5e6,1e7] [--f2f-sizes 1e6,5e6] [--resolutions default,paper] [--no-cloudcompare]
        [--work DIR] [--quick]
``--quick`` (a short check on a loaded machine): default resolution, 1e5 and 1e6 points, 2 repeats, 1 uncapped.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CLOUDCOMPARE = "CloudCompare"


#: points per view of the work-per-point run's merged views
VIEW_POINTS = 1_000_000


def log(line: str) -> None:
    print(f"[bench_scan {time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def load() -> float:
    return round(os.getloadavg()[0], 2)


def timed_process(command: list[str], env: dict[str, str] | None = None) -> dict:
    """Run ``command`` under /usr/bin/time -v: wall s, CPU s (user + system: on a loaded machine the steadier
    figure), peak RSS MB, exit status, load at start and end."""
    start_load = load()
    done = subprocess.run(["/usr/bin/time", "-v", *command], capture_output=True, text=True, timeout=3600,
                          env={**os.environ, **(env or {})})  # fmt: skip
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (?:(\d+):)?(\d+):([\d.]+)", done.stderr)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
    cpu = sum(float(m) for m in re.findall(r"(?:User|System) time \(seconds\): ([\d.]+)", done.stderr))
    seconds = (int(wall.group(1) or 0) * 3600 + int(wall.group(2)) * 60 + float(wall.group(3))) if wall else np.nan
    if done.returncode != 0:
        log(f"FAILED ({done.returncode}): {' '.join(command)}\n{done.stdout[-1500:]}\n{done.stderr[-1500:]}")
    return {"wall_s": seconds, "cpu_s": cpu, "peak_rss_mb": int(rss.group(1)) / 1024 if rss else np.nan,
            "status": done.returncode, "load_start": start_load, "load_end": load()}  # fmt: skip


def summary(runs: list[dict]) -> dict:
    ok = [r for r in runs if r["status"] == 0]
    return {"runs": len(runs), "ok": len(ok), "median_wall_s": float(np.median([r["wall_s"] for r in ok])) if ok
            else None, "median_peak_rss_mb": float(np.median([r["peak_rss_mb"] for r in ok])) if ok else None,
            "median_cpu_s": float(np.median([r["cpu_s"] for r in ok])) if ok else None,
            "walls_s": [r["wall_s"] for r in runs], "loads": [r["load_start"] for r in runs]}  # fmt: skip


# ------------------------------------------------------------------------------------------------ data
def truth_field(points: np.ndarray) -> np.ndarray:
    """(N,) mm: a smooth boundary-effect-like normal displacement over the skin's bounding box (about 1 mm)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    x, y = ((points[:, :2] - lo[:2]) / (hi[:2] - lo[:2])).T
    bump = np.exp(-((x - 0.6) ** 2 + (y - 0.55) ** 2) / (2 * 0.2**2))
    return 0.8 * x * x * y + 0.6 * x * y * y - 0.5 * x**3 + 0.4 * y**3 + 0.5 * bump


def prepare(resolution: str, work: Path, max_points: int, sizes: list[int]) -> dict:
    """Model, toy bases with the prepared skin, mesh PLY, the scan clouds (part frame) and their markers."""
    from hood_decomp.core.fe.model import skin_surface
    from hood_decomp.core.method.bases import build_bases
    from hood_decomp.core.scan.scan_field import ScanFieldEstimator
    from hood_decomp.io.bases import save_bases
    from hood_decomp.io.model_files import load_model
    from hood_decomp.io.ply import write_ply, write_skin_mesh
    from hood_decomp.synthetic.scanner import ScannerConfig, synthesize_scan
    from tests.toy_models import full_factorial, make_ensemble, make_reduced_model

    directory = work / resolution
    directory.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "hood_decomp.cli", "model", "--preset", "hood", "--resolution", resolution,
                    "--out", str(directory / "model")], check=True, capture_output=True)  # fmt: skip
    skin = skin_surface(load_model(directory / "model"))
    info: dict = {"skin_nodes": skin.n_nodes, "load_at_prepare": load()}
    start = time.perf_counter()
    ScanFieldEstimator().fit(skin)
    info["prepare_skin_s"] = time.perf_counter() - start
    log(f"{resolution}: {skin.n_nodes} skin nodes, skin prepared in {info['prepare_skin_s']:.2f} s (load {load()})")
    model = make_reduced_model(skin, seed=1, n_bilateral=2, n_pads=1, springs_per_pad=1)
    states, rank = full_factorial(3)
    bases = build_bases(make_ensemble(model, states, rank), skin, model, n_components=6, epsilon=0.01)
    start = time.perf_counter()
    save_bases(directory / "bases.h5", bases)
    info["save_bases_s"] = time.perf_counter() - start
    info["bases_mb"] = (directory / "bases.h5").stat().st_size / 2**20
    write_skin_mesh(directory / "mesh.ply", skin)
    truth = truth_field(skin.points)
    np.save(directory / "truth.npy", truth)
    # ~20 % of a hood scan is fixture background and outliers: ask for that much less on the skin
    scan = synthesize_scan(skin, skin.normals * truth[:, None],
                           ScannerConfig(n_points=int(max_points / 1.2), noise_mm=0.05), seed=7)  # fmt: skip
    rotation, shift = scan.true_transform[:3, :3], scan.true_transform[:3, 3]
    points = scan.points @ rotation.T + shift
    np.save(directory / "markers.npy", np.stack([scan.markers @ rotation.T + shift, scan.markers_nominal]))
    del scan
    rng = np.random.default_rng(11)
    info["clouds"] = {}
    for size in sizes:
        chosen = points if size >= points.shape[0] else points[np.sort(rng.choice(points.shape[0], size, False))]
        path = directory / f"cloud_{size}.ply"
        write_ply(path, chosen)
        info["clouds"][size] = {"path": str(path), "points": int(chosen.shape[0])}
        log(f"{resolution}: cloud of {chosen.shape[0]:,} points written")
    return info


# ------------------------------------------------------------------------------------------------ child
def child(resolution_dir: str, cloud: str, repeats: int) -> None:
    """One scan size in a fresh process: per-scan timings, scan-step peak memory, accuracy. Prints one JSON line."""
    from hood_decomp.core.scan import kernels
    from hood_decomp.core.scan.scan_field import field_from_scan, prepared_estimator
    from hood_decomp.io.bases import load_bases
    from hood_decomp.io.ply import read_scan
    from hood_decomp.ros.node_common import keep_freed_memory, small_pages_from_now

    keep_freed_memory()  # the scan node's process settings (node_common.spin, on_configure)
    directory = Path(resolution_dir)
    t0 = time.perf_counter()
    bases = load_bases(directory / "bases.h5")
    estimator = prepared_estimator(bases.skin)  # the prepared skin read from the file
    load_s = time.perf_counter() - t0
    small_pages_from_now()
    kernels.load()  # as the scan node does in its warm-up: the compiled path at every size (loaded at the first call)
    t0 = time.perf_counter()
    points = read_scan(cloud).points
    read_s = time.perf_counter() - t0
    markers, nominal = np.load(directory / "markers.npy")
    truth = np.load(directory / "truth.npy")

    def run():
        return field_from_scan(bases.skin, points, markers_mm=markers, markers_nominal_mm=nominal,
                               estimator=estimator, min_coverage=0.0)  # fmt: skip

    status = Path("/proc/self/status")
    before = int(re.search(r"VmRSS:\s+(\d+)", status.read_text()).group(1)) / 1024
    Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM: the peak below is the scan step's
    t0 = time.perf_counter()
    field, _ = run()
    first = time.perf_counter() - t0
    peak = int(re.search(r"VmHWM:\s+(\d+)", status.read_text()).group(1)) / 1024
    times, loads = [], []
    for _ in range(repeats):
        loads.append(load())
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    error = field.normal_displacement - truth
    seen = np.isfinite(error)
    print(json.dumps({
        "points": int(points.shape[0]), "load_prepared_s": load_s, "read_ply_s": read_s, "first_s": first,
        "times_s": times, "median_s": float(np.median(times)), "loads": loads,
        "rss_before_mb": before, "scan_peak_rss_mb": peak, "coverage": field.coverage,
        "rms_error_mm": float(np.sqrt(np.mean(error[seen] ** 2))), "noise_rms_mm": field.noise_rms,
    }))  # fmt: skip


def linearity_child(resolution_dir: str, cloud: str, sizes: list[int], views: list[int], rounds: int) -> None:
    """The scan step's work per point, one process, one thread, CPU seconds per field, for two ways a cloud grows:
    one view made denser (clouds of ``sizes`` points drawn from ``cloud`` in its order, as the per-size clouds are)
    and more views (``views`` counts of 1M-point views, each drawn from ``cloud`` on its own, one after the other in
    one cloud, as a robot's views of the part are merged). The clouds are interleaved round by round (forwards, then
    backwards) so that a drifting load and the heap's state reach all alike. Prints one JSON line."""
    from hood_decomp.core.scan import kernels
    from hood_decomp.core.scan.scan_field import prepared_estimator
    from hood_decomp.io.bases import load_bases
    from hood_decomp.io.ply import read_scan
    from hood_decomp.ros.node_common import keep_freed_memory, small_pages_from_now

    keep_freed_memory()
    kernels.threads = lambda: 1  # work, not wall: one thread, so the other engineers' load does not split it
    estimator = prepared_estimator(load_bases(Path(resolution_dir) / "bases.h5").skin)
    kernels.load()
    small_pages_from_now()
    full = read_scan(cloud).points
    rng = np.random.default_rng(11)

    def drawn(size: int) -> np.ndarray:
        return full if size >= full.shape[0] else full[np.sort(rng.choice(full.shape[0], size, False))]

    merged = np.concatenate([drawn(VIEW_POINTS) for _ in range(max(views))]) if views else full[:0]
    clouds = {**{("denser", s): drawn(s) for s in sizes}, **{("views", k): merged[: k * VIEW_POINTS] for k in views}}
    keys = list(clouds)
    for key in keys:
        estimator.field(clouds[key])
    cpu: dict[tuple[str, int], list[float]] = {key: [] for key in keys}
    for r in range(rounds):
        for key in keys if r % 2 == 0 else keys[::-1]:
            t0 = time.process_time()
            estimator.field(clouds[key])
            cpu[key].append(time.process_time() - t0)
    print(json.dumps({series: {"points": [int(clouds[key].shape[0]) for key in keys if key[0] == series],
                               "median_cpu_s": [float(np.median(cpu[key])) for key in keys if key[0] == series],
                               "cpu_s": [cpu[key] for key in keys if key[0] == series]}
                      for series in ("denser", "views")}))  # fmt: skip


# What `hood-decomp estimate --bases B --scan S --json J` does (cli/estimate.py, cli/_common.py: read_fields), by
# phase, in a fresh interpreter (python -c): nothing is imported before the first mark.
PHASES_SCRIPT = """
import time
wall, cpu, out = time.perf_counter(), time.process_time(), {}
def mark(name):
    global wall, cpu
    out[name] = [time.perf_counter() - wall, time.process_time() - cpu]
    wall, cpu = time.perf_counter(), time.process_time()
import json, sys
from pathlib import Path
from hood_decomp.cli import estimate as verb
from hood_decomp.cli._common import write_json
from hood_decomp.core.method.bases import estimate_field
from hood_decomp.core.scan.fusion import fuse_views
from hood_decomp.core.scan.scan_field import prepared_estimator
from hood_decomp.io.bases import bases_provenance, load_bases
from hood_decomp.io.scans import scan_file_view
mark("imports")
bases = load_bases(sys.argv[1])
mark("bases")
prepared_estimator(bases.skin)
mark("prepared_skin")
view = scan_file_view(sys.argv[2])
mark("read_ply")
field = fuse_views(bases.skin, [view], min_coverage=0.0, min_view_coverage=0.0).field
mark("scan_path")
estimate = estimate_field(bases, field, "contact", 0.0, 0.0)
mark("estimate")
payload = verb.estimate_payload(estimate, bases.pca.n_bilateral_)
payload.update(bases_provenance(bases))
write_json(Path(sys.argv[3]), payload)
mark("json")
print("PHASES", json.dumps({**out, "numba_loaded": "numba" in sys.modules}))
"""


def cold_phases(bases: Path, cloud: str, out: Path, repeats: int, env: dict[str, str] | None = None) -> dict:
    """Median wall and CPU s per phase of :data:`PHASES_SCRIPT` over ``repeats`` fresh processes."""
    runs = []
    for _ in range(repeats):
        done = subprocess.run([sys.executable, "-c", PHASES_SCRIPT, str(bases), cloud, str(out)], capture_output=True,
                              text=True, timeout=3600, env={**os.environ, **(env or {})})  # fmt: skip
        if done.returncode != 0:
            log(f"phases FAILED: {done.stderr[-1500:]}")
            continue
        line = next(row for row in done.stdout.splitlines() if row.startswith("PHASES "))
        runs.append(json.loads(line[len("PHASES "):]))
    if not runs:
        return {}
    names = [name for name in runs[0] if name != "numba_loaded"]
    result = {name: {"wall_s": float(np.median([r[name][0] for r in runs])),
                     "cpu_s": float(np.median([r[name][1] for r in runs]))} for name in names}  # fmt: skip
    result["total"] = {kind: float(np.median([sum(r[n][k] for n in names) for r in runs]))
                       for k, kind in enumerate(("wall_s", "cpu_s"))}  # fmt: skip
    result["numba_loaded"] = runs[0]["numba_loaded"]
    result["runs"] = len(runs)
    return result


# ------------------------------------------------------------------------------------------------ main
def cloudcompare(cloud: str, mesh: str, out: str, cap: bool) -> list[str]:
    return [CLOUDCOMPARE, "-SILENT", "-AUTO_SAVE", "OFF", "-C_EXPORT_FMT", "PLY", "-O", cloud, "-O", mesh,
            "-C2M_DIST", *(["-MAX_DIST", "5"] if cap else []), "-SAVE_CLOUDS", "FILE", out]  # fmt: skip


def linear_fit(points: np.ndarray, seconds: np.ndarray) -> dict:
    """a + b x points over the sizes from 1M on; marginal ns/point between neighbouring sizes, at the bottom (the two
    smallest sizes >= 1M) and at the top (the two largest), and top / bottom."""
    order = np.argsort(points)
    p, t = points[order], seconds[order]
    keep = p >= 1_000_000
    p, t = (p[keep], t[keep]) if keep.sum() >= 2 else (p, t)
    if p.size < 2:
        return {}
    b, a = np.polyfit(p, t, 1)
    marginal = [(t[k + 1] - t[k]) / (p[k + 1] - p[k]) * 1e9 for k in range(p.size - 1)]
    return {"a_s": float(a), "b_ns_per_point": float(b * 1e9), "sizes": [int(x) for x in p],
            "marginal_ns_per_point": {f"{int(p[k])}-{int(p[k + 1])}": float(m) for k, m in enumerate(marginal)},
            "marginal_bottom_ns": float(marginal[0]), "marginal_top_ns": float(marginal[-1]),
            "top_over_bottom": float(marginal[-1] / marginal[0]) if marginal[0] > 0 else None}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--uncapped-repeats", type=int, default=3, help="runs of uncapped CloudCompare at >= 5M")
    parser.add_argument("--sizes", default="1e5,1e6,2e6,5e6,1e7")
    parser.add_argument("--f2f-sizes", default="1e6,5e6", help="sizes of the file-to-file, cold-phase and "
                        "CloudCompare runs (the per-scan runs take every size)")
    parser.add_argument("--resolutions", default="default,paper")
    parser.add_argument("--no-cloudcompare", action="store_true")
    parser.add_argument("--quick", action="store_true", help="a short check: default resolution, 1e5 and 1e6 "
                        "points, 2 repeats, 1 uncapped CloudCompare run")
    parser.add_argument("--work", default=None, help="work directory (default: a temporary one, removed)")
    parser.add_argument("--linearity-sizes", default="1e6,2e6,3e6,4e6,6e6,8e6,1e7",
                        help="sizes of the work-per-point run (one process, one thread, CPU time, drawn from the "
                        "largest cloud); empty: none")
    parser.add_argument("--linearity-views", default="1,2,4,6,8,10",
                        help="view counts of the work-per-point run's merged 1M-point views; empty: none")
    parser.add_argument("--linearity-rounds", type=int, default=7)
    parser.add_argument("--child", nargs=2, metavar=("RESOLUTION_DIR", "CLOUD"), help=argparse.SUPPRESS)
    parser.add_argument("--linearity-child", nargs=2, metavar=("RESOLUTION_DIR", "CLOUD"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    linearity_sizes = [int(float(s)) for s in args.linearity_sizes.split(",") if s]
    linearity_views = [int(k) for k in args.linearity_views.split(",") if k]
    if args.child:
        child(*args.child, args.repeats)
        return 0
    if args.linearity_child:
        linearity_child(*args.linearity_child, linearity_sizes, linearity_views, args.linearity_rounds)
        return 0
    if args.quick:
        args.resolutions, args.sizes, args.f2f_sizes = "default", "1e5,1e6", "1e6"
        args.repeats, args.uncapped_repeats = 2, 1
    sizes = [int(float(s)) for s in args.sizes.split(",")]
    f2f_sizes = {int(float(s)) for s in args.f2f_sizes.split(",")} & set(sizes)
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_scan_"))
    have_cc = not args.no_cloudcompare and shutil.which(CLOUDCOMPARE) is not None
    results: dict = {"date": time.strftime("%Y-%m-%d %H:%M"), "cpus": os.cpu_count(), "sizes": sizes,
                     "f2f_sizes": sorted(f2f_sizes), "repeats": args.repeats, "load_at_start": load(),
                     "resolutions": {}}  # fmt: skip
    hood = [shutil.which("hood-decomp")] if shutil.which("hood-decomp") else [sys.executable, "-m", "hood_decomp.cli"]
    out_dir = ROOT / "benchmarks" / "out"
    out_dir.mkdir(exist_ok=True)
    rows, f2f_rows = [], []
    try:
        for resolution in args.resolutions.split(","):
            directory = work / resolution
            if args.work and (directory / "bases.h5").exists() and all(
                    (directory / f"cloud_{s}.ply").exists() for s in sizes):  # fmt: skip
                info = json.loads((directory / "info.json").read_text())  # reuse a prepared work directory
                info["clouds"] = {int(k): v for k, v in info["clouds"].items()}
            else:
                info = prepare(resolution, work, max(sizes), sizes)
                (directory / "info.json").write_text(json.dumps(info, default=str))
            bases = directory / "bases.h5"
            per_size = {}
            for size in sizes:
                cloud = info["clouds"][size]["path"]
                n = info["clouds"][size]["points"]
                entry: dict = {"points": n}
                done = subprocess.run([sys.executable, __file__, "--repeats", str(args.repeats), "--child",
                                       str(directory), cloud], capture_output=True, text=True, check=True)  # fmt: skip
                entry["per_scan"] = ps = json.loads(done.stdout.strip().splitlines()[-1])
                rows.append((resolution, n, ps["median_s"], ps["first_s"], ps["scan_peak_rss_mb"], ps["rms_error_mm"],
                             ps["coverage"], float(np.median(ps["loads"]))))  # fmt: skip
                log(f"{resolution} {n:,}: per scan {ps['median_s']:.3f} s (load {load()})")
                if size in f2f_sizes:
                    estimate = [*hood, "estimate", "--bases", str(bases), "--scan", cloud, "--min-coverage", "0",
                                "--json", str(directory / "estimate.json")]  # fmt: skip
                    runs, cc_runs, cc_u_runs = [], [], []
                    cc_out = str(directory / "cc_out.ply")
                    cc_env = {"QT_QPA_PLATFORM": "offscreen"}
                    for k in range(args.repeats):  # interleaved run by run: both see the same load
                        runs.append(timed_process(estimate))
                        if have_cc:
                            cc_runs.append(timed_process(cloudcompare(cloud, str(directory / "mesh.ply"), cc_out,
                                                                      True), cc_env))  # fmt: skip
                            if k < (args.repeats if size < 5_000_000 else args.uncapped_repeats):
                                cc_u_runs.append(timed_process(cloudcompare(cloud, str(directory / "mesh.ply"), cc_out,
                                                                            False), cc_env))  # fmt: skip
                    Path(cc_out).unlink(missing_ok=True)
                    entry["file_to_file"] = ff = summary(runs)
                    if have_cc:
                        entry["cloudcompare_capped"] = summary(cc_runs)
                        entry["cloudcompare_uncapped"] = summary(cc_u_runs)
                    entry["cold_phases"] = cold_phases(bases, cloud, directory / "phases.json", args.repeats)
                    cc = entry.get("cloudcompare_capped", {}).get("median_wall_s")
                    ccu = entry.get("cloudcompare_uncapped", {}).get("median_wall_s")
                    f2f_rows.append((resolution, n, ff["median_wall_s"], ff["median_peak_rss_mb"], cc,
                                     entry.get("cloudcompare_capped", {}).get("median_peak_rss_mb"), ccu,
                                     float(np.median(ff["loads"])) if ff["loads"] else None, entry["cold_phases"],
                                     ff["median_cpu_s"], entry.get("cloudcompare_capped", {}).get("median_cpu_s")))
                    log(f"{resolution} {n:,}: file to file {ff['median_wall_s']} s, CC capped {cc}, uncapped {ccu} "
                        f"(load {load()})")
                per_size[size] = entry
            points = np.array([per_size[s]["points"] for s in sizes], dtype=float)
            info["fit"] = linear_fit(points, np.array([per_size[s]["per_scan"]["median_s"] for s in sizes]))
            top = per_size[max(sizes)]["per_scan"]
            info["linearity"] = {**info["fit"], "scan_peak_rss_mb_at_largest": top["scan_peak_rss_mb"],
                                 "largest_points": top["points"]}  # fmt: skip
            info["sizes"] = per_size
            largest = info["clouds"][max(sizes)]
            if (linearity_sizes or linearity_views) and max(linearity_sizes, default=0) <= largest["points"]:
                done = subprocess.run([sys.executable, __file__, "--linearity-sizes", args.linearity_sizes,
                                       "--linearity-views", args.linearity_views, "--linearity-rounds",
                                       str(args.linearity_rounds), "--linearity-child", str(directory),
                                       largest["path"]], capture_output=True, text=True, check=True)  # fmt: skip
                work_run = json.loads(done.stdout.strip().splitlines()[-1])
                info["work_per_point"] = {series: {**run, "fit": linear_fit(np.array(run["points"], float),
                                                                            np.array(run["median_cpu_s"]))}
                                          for series, run in work_run.items() if run["points"]}  # fmt: skip
                log(f"{resolution}: work per point measured (load {load()})")
            results["resolutions"][resolution] = info
            (out_dir / "bench_scan.json").write_text(json.dumps(results, indent=1, default=str))
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    results["load_at_end"] = load()
    (out_dir / "bench_scan.json").write_text(json.dumps(results, indent=1, default=str))

    def show(value: float | None, fmt: str) -> str:
        return "-" if value is None or not np.isfinite(value) else format(value, fmt)

    print("Per scan (prepared skin loaded, compiled path as in a node; median of the repeats after a first call, "
          "which loads numba):")
    print(f"{'resolution':<10} {'points':>11} {'scan s':>7} {'first s':>7} {'scan MB':>7} {'RMS mm':>7} {'cover':>6} "
          f"{'load':>5}")
    for r in rows:
        print(f"{r[0]:<10} {r[1]:>11,} {show(r[2], '.3f'):>7} {show(r[3], '.3f'):>7} {show(r[4], '.0f'):>7} "
              f"{show(r[5], '.4f'):>7} {show(r[6], '.3f'):>6} {r[7]:>5}")
    print("\nFile to file, fresh processes (median wall s / CPU s / peak MB), CloudCompare C2M with -MAX_DIST 5 and "
          "without (wall s); faster by wall time:")
    print(f"{'resolution':<10} {'points':>11} {'hood-decomp':>20} {'CC -MAX_DIST 5':>20} {'CC uncapped':>11} "
          f"{'faster':>22} {'load':>5}")
    for r in f2f_rows:
        verdict = "-" if r[2] is None or r[4] is None else (
            f"hood-decomp {r[4] / r[2]:.2f} x" if r[2] < r[4] else f"CloudCompare {r[2] / r[4]:.2f} x")
        print(f"{r[0]:<10} {r[1]:>11,} {show(r[2], '.2f'):>6} / {show(r[9], '.2f'):>5} / {show(r[3], '.0f'):>4} "
              f"{show(r[4], '.2f'):>6} / {show(r[10], '.2f'):>5} / {show(r[5], '.0f'):>4} {show(r[6], '.2f'):>11} "
              f"{verdict:>22} {show(r[7], '.1f'):>5}")
    print("\nCold `estimate --scan` by phase (fresh process, median wall s / CPU s):")
    for r in f2f_rows:
        phases = r[8]
        if phases:
            text = ", ".join(f"{name} {v['wall_s']:.2f}/{v['cpu_s']:.2f}" for name, v in phases.items()
                             if isinstance(v, dict))  # fmt: skip
            print(f"{r[0]:<10} {r[1]:>11,}: {text}; numba loaded: {phases['numba_loaded']}")
    for resolution, info in results["resolutions"].items():
        fit = info["linearity"]
        if not fit.get("sizes"):
            continue
        ratio = fit["top_over_bottom"]
        print(f"{resolution}: prepare skin {info['prepare_skin_s']:.2f} s; per scan over {fit['sizes']} points = "
              f"{fit['a_s'] * 1e3:.1f} ms + {fit['b_ns_per_point']:.1f} ns x points; marginal "
              f"{fit['marginal_bottom_ns']:.1f} ns/point at the bottom, {fit['marginal_top_ns']:.1f} at the top "
              f"(ratio {show(ratio, '.2f')}, target <= 1.15); scan-step peak "
              f"{fit['scan_peak_rss_mb_at_largest']:.0f} MB at {fit['largest_points']:,} points (target < 1024)")
    for resolution, info in results["resolutions"].items():
        for series, work in info.get("work_per_point", {}).items():
            if not work["fit"]:
                continue
            marginal = ", ".join(f"{k} {v:.1f}" for k, v in work["fit"]["marginal_ns_per_point"].items())
            how = "one view made denser" if series == "denser" else f"merged views of {VIEW_POINTS:,} points"
            print(f"{resolution}, work per point, {how} (one thread, CPU time, one process, interleaved): "
                  f"{work['fit']['a_s'] * 1e3:.1f} ms + {work['fit']['b_ns_per_point']:.1f} ns x points; marginal "
                  f"ns/point {marginal}; top / bottom {show(work['fit']['top_over_bottom'], '.2f')} (target "
                  f"0.85-1.15)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
