"""What the physical responses in a bases file cost (issue 15 / 21: ``/physics``, written by ``bases --model``).

Builds the built-in hood at ``--resolution`` (tests/conftest.py ``_hood_case``; default resolution takes a few GB:
run it under the memory lock), its responses (``model_physics``: one factorisation and one per sheet group, timed),
and writes the same bases twice, without and with the group. Then, alternating the two files ``--repeat`` times:
``load_bases(mapped=True)`` in this process (page cache warm; wall and CPU time; the group's normal parts are read,
checked and hashed on load) and a one-off ``hood-decomp estimate --field`` in a fresh process (wall time and peak RSS by
``/usr/bin/time``). Also timed once: the group's physics_id hash alone and the first read of its 3D parts
(``PhysicalResponses.with_3d``, what ``--components xyz`` and ``calibrate`` pay). Prints a table of medians and
writes benchmarks/out/physics_file_<resolution>.json. From the repository root:
    OPENBLAS_NUM_THREADS=1 scripts/with-env python benchmarks/bench_physics_file.py --resolution coarse
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hood_decomp.core.fe.ensemble import solve_members  # noqa: E402
from hood_decomp.core.loop.calibration import model_physics  # noqa: E402
from hood_decomp.core.types import DisplacementField, FieldErrorModel  # noqa: E402
from hood_decomp.io import bases as bases_io  # noqa: E402
from hood_decomp.io.fields import write_field  # noqa: E402
from tests.conftest import _hood_case  # noqa: E402

OUT = ROOT / "benchmarks" / "out"


def log(message: str) -> None:
    print(f"[bench_physics_file {time.strftime('%H:%M:%S')}] {message}", flush=True)


def one_off_estimate(bases: Path, field: Path, out: Path) -> tuple[float, float]:
    """(wall s, peak RSS MB) of `hood-decomp estimate --bases --field --json` in a fresh process."""
    done = subprocess.run(["/usr/bin/time", "-v", sys.executable, "-m", "hood_decomp.cli", "estimate", "--bases",
                           str(bases), "--field", str(field), "--json", str(out)], capture_output=True, text=True,
                          check=True)
    wall = re.search(r"Elapsed \(wall clock\) time .*: (?:(\d+):)?(\d+(?:\.\d+)?)$", done.stderr, re.M)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
    return 60 * float(wall.group(1) or 0) + float(wall.group(2)), int(rss.group(1)) / 1024


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", choices=("coarse", "default"), default="coarse")
    parser.add_argument("--repeat", type=int, default=5, help="loads and one-off estimates per file")
    parser.add_argument("--out", type=Path, default=None, help="JSON (default benchmarks/out/physics_file_RES.json)")
    args = parser.parse_args()
    out = args.out or OUT / f"physics_file_{args.resolution}.json"
    record: dict = {"date": time.strftime("%Y-%m-%d %H:%M"), "args": vars(args) | {"out": str(out)},
                    "load_average_start": os.getloadavg()}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        log(f"building the {args.resolution} hood, its ensemble and bases")
        case = _hood_case(args.resolution, root)
        started = time.perf_counter()
        physics = model_physics(case.model, case.reduced, case.solver)
        record["responses_s"] = time.perf_counter() - started
        log(f"responses (model_physics) {record['responses_s']:.1f} s")
        files = {"without": root / "without.h5", "with": root / "with.h5"}
        bases_io.save_bases(files["without"], dataclasses.replace(case.bases, physics=None))
        bases_io.save_bases(files["with"], dataclasses.replace(case.bases, physics=physics))
        record["size_mb"] = {k: p.stat().st_size / 1e6 for k, p in files.items()}
        normal, three_d = bases_io._physics_arrays(physics)
        with h5py.File(files["with"], "r") as h5:  # as stored (the 3D parts float32)
            record["group_mb"] = {part: sum(h5[f"physics/{name}"].nbytes for name in names) / 1e6
                                  for part, names in (("normal", normal), ("3d", three_d))}
        record["shape"] = {"N": case.skin.n_nodes, "B": case.reduced.n_bilateral, "S": int(case.reduced.k.size),
                           "G": len(physics.thickness)}
        rng = np.random.default_rng(21)
        member = solve_members(case.reduced, rng.uniform(case.model.lower, case.model.upper)[None])
        values = member.normal_displacement[0] + rng.normal(0.0, 0.02, case.skin.n_nodes)
        field = root / "field.vtu"
        write_field(field, case.skin, DisplacementField(case.skin.model_id, values, 1.0, 0.02,
                                                        FieldErrorModel.stated(0.02, values.size)))
        loads: dict[str, list[float]] = {k: [] for k in files}
        load_cpu: dict[str, list[float]] = {k: [] for k in files}  # CPU s: less moved by a loaded machine
        estimates: dict[str, list[tuple[float, float]]] = {k: [] for k in files}
        for _ in range(args.repeat):
            for kind, path in files.items():
                started, cpu = time.perf_counter(), time.process_time()
                loaded = bases_io.load_bases(path, mapped=True)
                loads[kind].append(time.perf_counter() - started)
                load_cpu[kind].append(time.process_time() - cpu)
                del loaded
                estimates[kind].append(one_off_estimate(path, field, root / f"{kind}.json"))
        record["factors"] = {k: sorted(json.loads((root / f"{k}.json").read_text())["model_factors_mm"])
                             for k in files}
        loaded = bases_io.load_bases(files["with"], mapped=True)
        arrays = {name: np.asarray(a) for name, a in normal.items()}
        started = time.perf_counter()
        bases_io.physics_id("0" * 16, tuple(physics.thickness), arrays)
        record["hash_normal_s"] = time.perf_counter() - started
        started = time.perf_counter()
        loaded.physics.with_3d()
        record["first_3d_read_s"] = time.perf_counter() - started
        record["load_s"], record["load_cpu_s"] = loads, load_cpu
        record["estimate"] = {k: {"wall_s": [w for w, _ in v], "rss_mb": [r for _, r in v]} for k, v in
                              estimates.items()}
    record["load_average_end"] = os.getloadavg()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))
    med = np.median
    print(f"{args.resolution} (N {record['shape']['N']}, B {record['shape']['B']}, S {record['shape']['S']}, "
          f"G {record['shape']['G']}); responses {record['responses_s']:.1f} s; group: normal "
          f"{record['group_mb']['normal']:.1f} MB, 3D {record['group_mb']['3d']:.1f} MB; hash of the normal parts "
          f"{record['hash_normal_s'] * 1e3:.0f} ms; first 3D read {record['first_3d_read_s'] * 1e3:.0f} ms")
    print(f"{'file':<8} {'MB':>8} {'load s (median)':>16} {'load CPU s':>11} {'estimate s (median)':>20} "
          f"{'peak RSS MB (median)':>21}")
    for kind in files:
        print(f"{kind:<8} {record['size_mb'][kind]:>8.1f} {med(loads[kind]):>16.3f} {med(load_cpu[kind]):>11.3f} "
              f"{med(record['estimate'][kind]['wall_s']):>20.2f} {med(record['estimate'][kind]['rss_mb']):>21.0f}")
    print(f"factors: {record['factors']}; load average {record['load_average_start']} -> "
          f"{record['load_average_end']}; JSON {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
