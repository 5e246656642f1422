"""Named faults injected into the method, and the tests that catch each (issue 14's list).

Each fault is one textual change to one module of a copy of the package (the working tree is never touched); the
fast tests of the method and the close loop then run against the copy. A fault is caught when at least one test
fails; the table names those tests. A control run without any fault must pass first, or nothing here means anything.

    scripts/with-env python benchmarks/fault_injection.py [--only NAME ...] [--tests PATH ...]

Prints a table and writes benchmarks/out/fault_injection.json. Takes a few minutes (one pytest run per fault).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ros2_ws" / "src" / "hood_decomp" / "hood_decomp"
OUT = ROOT / "benchmarks" / "out" / "fault_injection.json"
# The fast tests of the method and the close loop (the slow default-resolution ones are left to CI).
TESTS = ("tests/core/method", "tests/core/loop")


@dataclasses.dataclass(frozen=True)
class Fault:
    name: str
    what: str
    module: str  # path below the package
    old: str
    new: str


FAULTS = (
    Fault("centring", "eq. 5 without its centring term: values = c @ states (no mean_state_)",
          "core/method/estimation.py", "values=basis.mean_state_ + coeff @ states,", "values=coeff @ states,"),
    Fault("eq6_partner", "eq. 6 without the inverse partner: d_i = |c_i B_i|",
          "core/method/decomposition.py", "    idx = idx[idx >= 0]\n    return np.linalg.norm(",
          "    idx = idx[:1]\n    return np.linalg.norm("),
    Fault("std_x10", "the contact estimator states 10x its standard deviation",
          "core/method/contact_estimation.py", "            std=out_std,", "            std=10.0 * out_std,"),
    Fault("std_div10", "the contact estimator states a tenth of its standard deviation",
          "core/method/contact_estimation.py", "            std=out_std,", "            std=out_std / 10.0,"),
    Fault("contact_flag", "pads in light contact reported lifted (lift threshold 20 std instead of 2)",
          "core/method/contact_estimation.py", "LIFTED_SIGMAS = 2.0", "LIFTED_SIGMAS = 20.0"),
    Fault("step5_off", "step 5 never coarsens (default thresholds have no effect)",
          "core/method/decomposition.py",
          "if magnitude[smallest] >= min_share * magnitude.sum() or magnitude[smallest] > max_removed_rms_mm:",
          "if True:"),
    Fault("step5_share_only", "step 5 removes by share alone, ignoring the 0.002 mm RMS guard",
          "core/method/decomposition.py",
          "if magnitude[smallest] >= min_share * magnitude.sum() or magnitude[smallest] > max_removed_rms_mm:",
          "if magnitude[smallest] >= min_share * magnitude.sum():"),
    Fault("non_candidate_found", "close-loop names a candidate for any residual it reduces at all (a missing effect "
          "outside the candidates is forced onto one)",
          "core/loop/close_loop.py", "PARTIAL_MIN = 0.75", "PARTIAL_MIN = 0.0"),
)


def run_tests(package: pathlib.Path, junit: pathlib.Path, tests: tuple[str, ...] = TESTS
              ) -> tuple[int, list[str], float]:
    """Run ``tests`` (not slow) with ``package`` first on the path; (exit status, failed test ids, seconds)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(package.parent), str(ROOT), env.get("PYTHONPATH", "")])
    start = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "not slow",
                          f"--junitxml={junit}", *tests], cwd=ROOT, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    failed = []
    if junit.is_file():
        for case in ET.parse(junit).getroot().iter("testcase"):
            if case.find("failure") is not None or case.find("error") is not None:
                failed.append(f"{case.get('classname', '').replace('.', '/')}.py::{case.get('name')}")
    return run.returncode, failed, seconds


def inject(fault: Fault, workdir: pathlib.Path) -> pathlib.Path:
    """A copy of the package with ``fault`` applied; the copy's root folder is named hood_decomp."""
    copy = workdir / fault.name / "hood_decomp"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    path = copy / fault.module
    text = path.read_text()
    if text.count(fault.old) != 1:
        raise SystemExit(f"fault {fault.name}: expected the text once in {fault.module}, found it "
                         f"{text.count(fault.old)} times; update FAULTS to today's code")
    path.write_text(text.replace(fault.old, fault.new))
    return copy


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None, help="fault names to run (default: all)")
    parser.add_argument("--tests", nargs="*", default=list(TESTS), help=f"test paths to run (default: {TESTS})")
    args = parser.parse_args()
    tests = tuple(args.tests)
    faults = [f for f in FAULTS if args.only is None or f.name in args.only]
    rows = []
    with tempfile.TemporaryDirectory(prefix="hood_faults_") as tmp:
        work = pathlib.Path(tmp)
        control = work / "control" / "hood_decomp"
        shutil.copytree(PACKAGE, control, ignore=shutil.ignore_patterns("__pycache__"))
        status, failed, seconds = run_tests(control, work / "control.xml", tests)
        print(f"control (no fault): exit {status}, {len(failed)} failed, {seconds:.0f} s", flush=True)
        if status != 0:
            print("the control run fails; fix the tests first:\n  " + "\n  ".join(failed), file=sys.stderr)
            return 1
        for fault in faults:
            status, failed, seconds = run_tests(inject(fault, work), work / f"{fault.name}.xml", tests)
            rows.append({"fault": fault.name, "what": fault.what, "module": fault.module, "caught": bool(failed),
                         "caught_by": failed, "seconds": round(seconds, 1)})
            print(f"{fault.name:20s} {'CAUGHT' if failed else 'MISSED':7s} {len(failed):3d} failing test(s), "
                  f"{seconds:.0f} s", flush=True)
    print()
    print("| fault | caught | by (first three of the failing tests) |\n|---|---|---|")
    for row in rows:
        by = ", ".join(t.split("::")[-1] for t in row["caught_by"][:3]) or "-"
        print(f"| {row['fault']} | {'yes' if row['caught'] else 'NO'} | {by} |")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "tests": tests, "faults": rows}, indent=2))
    print(f"\nwritten: {OUT}")
    return 0 if all(row["caught"] for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
