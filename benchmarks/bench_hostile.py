"""Hostile and broken input (issue 18): the YAML alias bomb's time and memory, the bad-input matrix and the reader
fuzzing, each in a process of its own. Prints a table and writes benchmarks/out/hostile.json.

    scripts/with-env python benchmarks/bench_hostile.py

The bomb (tests/bad_inputs.py, like the issue's 394-byte one): 421 bytes of nested aliases, 9 levels of 9 aliases each
(9**10 = 3.5e9 leaves once expanded), given
as model.yaml to `hood-decomp simulate`; wall time and peak RSS (ru_maxrss of the child) of the whole command,
Python start-up and imports included, and of a bare `python -c pass` for reference.
"""

from __future__ import annotations

import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out"
sys.path.insert(0, str(ROOT))
from tests.bad_inputs import BOMB  # noqa: E402 - the repository root is on the path only from here


def _child(argv: list[str]) -> tuple[float, float, subprocess.CompletedProcess]:
    """Run argv; return wall seconds, the peak RSS in MB of the children so far (ru_maxrss of RUSAGE_CHILDREN: an
    upper bound of this child's) and the result."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    start = time.perf_counter()
    result = subprocess.run(argv, capture_output=True, text=True, timeout=3600)
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return seconds, max(peak, before) / 1024, result


def _refusal(model: Path) -> tuple[float, float]:
    """Seconds and peak MB of Python allocations (tracemalloc) of load_model refusing the bomb, imports done."""
    import tracemalloc

    from hood_decomp.errors import ModelError
    from hood_decomp.io.model_files import load_model

    tracemalloc.start()
    start = time.perf_counter()
    try:
        load_model(model)
    except ModelError:
        pass
    seconds = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return seconds, peak


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    results: dict[str, object] = {"date": time.strftime("%Y-%m-%d"), "load": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as directory:
        model = Path(directory) / "model"
        model.mkdir()
        (model / "model.yaml").write_text(BOMB)
        base_seconds, base_rss, _ = _child([sys.executable, "-c", "import hood_decomp.io.model_files"])
        seconds, rss, result = _child([sys.executable, "-m", "hood_decomp.cli", "simulate", "--model", str(model),
                                       "--out", str(Path(directory) / "f.vtu")])
        refusal_seconds, refusal_peak_mb = _refusal(model)
    results["bomb"] = {"bytes": len(BOMB.encode()), "exit": result.returncode, "stderr": result.stderr.strip(),
                       "seconds": round(seconds, 3), "peak_rss_mb": round(rss, 1),
                       "imports_alone_seconds": round(base_seconds, 3), "imports_alone_rss_mb": round(base_rss, 1),
                       "refusal_in_process_seconds": round(refusal_seconds, 4),
                       "refusal_in_process_peak_python_mb": round(refusal_peak_mb, 3)}
    for name, path in (("matrix", "tests/cli/test_bad_inputs.py"), ("fuzz", "tests/io/test_fuzz_readers.py")):
        seconds, _, result = _child([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", path])
        tail = result.stdout.strip().splitlines()[-1] if result.stdout.strip() else ""
        lines = [line for line in result.stdout.splitlines()
                 if re.match(r"\s*(fuzz |[\w.() /-]+\s+\d+ / \d+)", line)]
        results[name] = {"seconds": round(seconds, 1), "summary": tail, "lines": lines}
    (OUT / "hostile.json").write_text(json.dumps(results, indent=2) + "\n")
    bomb = results["bomb"]
    print(f"YAML alias bomb ({bomb['bytes']} bytes): exit {bomb['exit']} in {bomb['seconds']} s, peak RSS "
          f"{bomb['peak_rss_mb']} MB")
    print(f"  Python with the model reader's imports alone: {bomb['imports_alone_seconds']} s, "
          f"{bomb['imports_alone_rss_mb']} MB")
    print(f"  the refusal itself, in process: {bomb['refusal_in_process_seconds']} s, "
          f"{bomb['refusal_in_process_peak_python_mb']} MB of Python allocations at peak")
    print(f"  {bomb['stderr']}")
    for name in ("matrix", "fuzz"):
        print(f"{name}: {results[name]['summary']} (wall {results[name]['seconds']} s, pytest start-up included)")
        for line in results[name]["lines"]:
            print(f"  {line.strip()}")
    print(f"load average {results['load']:.1f}; wrote {OUT / 'hostile.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
