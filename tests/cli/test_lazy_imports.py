"""A one-off verb imports only what it uses (issue 19): start-up is most of a fresh `estimate --scan`.

Each test runs the verb in a fresh interpreter (the real ``hood_decomp.cli.main``) and lists the modules it imported.
"""

from __future__ import annotations

import json
import subprocess
import sys

# Measured costs of each in a fresh process on the project's machine class (issue 19): scipy.stats 0.9-1.3 s, numba
# 0.3-0.6 s plus about 0.6 s of CPU loading its cache and tearing down at exit (a one-off run repays it only from
# about 2M points, core/scan/kernels.py), scipy.linalg 0.1-0.4 s, meshio 0.14 s; the rest a verb on a scan never
# needs.
NOT_FOR_A_SMALL_SCAN = ("scipy.stats", "numba", "scipy.linalg", "scipy.spatial", "scipy.ndimage", "scipy.optimize",
                        "meshio", "sklearn", "open3d", "matplotlib", "rclpy", "dask", "rosbags")  # fmt: skip


def _imported_by(argv: list[str]) -> set[str]:
    """The top modules (and scipy's subpackages) ``hood-decomp argv`` imported in a fresh interpreter; asserts it
    succeeded."""
    script = ("import json, sys\nfrom hood_decomp.cli import main\n"
              f"status = main({argv!r})\nprint('MODULES', json.dumps(sorted(sys.modules)))\nsys.exit(status)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    line = next(row for row in done.stdout.splitlines() if row.startswith("MODULES "))
    return {".".join(name.split(".")[:2]) if name.startswith("scipy.") else name.split(".")[0]
            for name in json.loads(line[len("MODULES "):])}  # fmt: skip


def test_estimate_of_a_scan_imports_nothing_it_does_not_use(tiny_workspace, tmp_path):
    """Fails if `estimate --scan` of a small scan imports any of NOT_FOR_A_SMALL_SCAN: an eager module-level import
    came back (scipy.stats for the tests' p-values, scipy.linalg for fitting a PCA, meshio for .vtu files, ROS,
    plotting), or a scan below the compiled path's threshold loads numba in a fresh process."""
    ws = tiny_workspace
    modules = _imported_by(["estimate", "--bases", str(ws.bases), "--scan", str(ws.scan),
                            "--json", str(tmp_path / "estimate.json")])  # fmt: skip
    assert {"numpy", "h5py", "scipy.sparse", "scipy.special"} <= modules  # the listing sees what the verb does use
    assert not modules & set(NOT_FOR_A_SMALL_SCAN), sorted(modules & set(NOT_FOR_A_SMALL_SCAN))
    assert json.loads((tmp_path / "estimate.json").read_text())["parameters_mm"]



def test_help_imports_no_scipy():
    """Fails if `hood-decomp --help` imports scipy: since scipy 1.17 any scipy subpackage costs about 0.16 s (it clones
    every numpy submodule into its array-API namespace), half of what --help costs otherwise; a module-level
    ``import scipy.sparse`` or ``from scipy import special`` in a module a verb's parser imports brings it back."""
    script = ("import sys\nfrom hood_decomp.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit as done:\n"
              "    assert done.code == 0, done.code\n"
              "print('SCIPY', sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))\n")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    line = next(row for row in done.stdout.splitlines() if row.startswith("SCIPY "))
    assert line == "SCIPY []", line
