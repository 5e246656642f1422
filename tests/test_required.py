"""The required-parts switch itself (tests/required.py): a missing part skips a local run and fails CI by name."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import textwrap


def _run_with(tmp_path, env_ci: str | None) -> subprocess.CompletedProcess:
    test = tmp_path / "test_needs_part.py"
    test.write_text(textwrap.dedent("""
        from tests.required import require_import

        require_import("no_such_module_for_hood_decomp", "colcon build", "run inside scripts/with-env")


        def test_never_runs():
            pass
    """))
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "HOOD_DECOMP_REQUIRE_ALL")}
    if env_ci is not None:
        env["CI"] = env_ci
    root = pathlib.Path(__file__).resolve().parents[1]
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "--rootdir",
                           str(tmp_path), str(test)],
                          capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)


def test_local_run_skips_with_the_reason(tmp_path):
    """Fails if a local run (no CI variable) does not skip, or skips without naming the missing part."""
    run = _run_with(tmp_path, None)
    assert run.returncode in (0, 5), run.stdout[-2000:]  # 5: no test ran (the module was skipped)
    assert "1 skipped" in run.stdout
    assert "required part missing: colcon build" in run.stdout


def test_ci_fails_and_names_the_missing_part(tmp_path):
    """Fails if CI=true lets a missing required part pass as a skip (the whole ROS layer untested, CI green)."""
    run = _run_with(tmp_path, "true")
    assert run.returncode not in (0, 5), run.stdout[-2000:]
    assert "required part missing: colcon build" in run.stdout
    assert "skipped" not in run.stdout.splitlines()[-1]
