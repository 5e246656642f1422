"""`hood-decomp shift` as a user runs it: killed in the middle of the batch and rerun (the history continues without
duplicate rows), a broken part named in the report without stopping the batch, the report rendered in headless
Chromium, bad input refused with exit status 2."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time

import pytest

from tests.browser import check_rendered_report
from tests.hood20 import hood20
from tests.shift.conftest import write_fields

N_PARTS = 120


def _command(directory, out, *extra):
    return [sys.executable, "-m", "hood_decomp.cli", "shift", str(directory), "--bases", str(hood20().bases_path),
            "--out", str(out), "--workers", "1", "--baseline", "60", *extra]


def _rows(db_path):
    if not db_path.exists():
        return 0
    try:
        db = sqlite3.connect(db_path, timeout=5)
        return db.execute("SELECT COUNT(*) FROM parts").fetchone()[0]
    except sqlite3.OperationalError:  # the schema is being created
        return 0


@pytest.fixture(scope="module")
def shift_run(tmp_path_factory):
    """A shift killed (SIGKILL, with its Dask workers) after 30 parts, then rerun to the end."""
    root = tmp_path_factory.mktemp("shift")
    directory = write_fields(root / "fields", N_PARTS)
    (directory / "zz_broken.vtu").write_text("<VTKFile>not a field</VTKFile>\n")
    out = root / "out"
    db = out / "history.sqlite"
    first = subprocess.Popen(_command(directory, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             start_new_session=True)
    deadline = time.monotonic() + 300
    while _rows(db) < 30 and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(first.pid, signal.SIGKILL)
    first.wait(timeout=60)
    rows_at_kill = _rows(db)
    second = subprocess.run(_command(directory, out), capture_output=True, text=True, timeout=600)
    return root, out, rows_at_kill, second


def test_rerun_after_a_crash_continues_without_duplicates(shift_run):
    """Fails if the killed run had not been stopped mid-batch, if the rerun processes a part the history already held,
    loses one, or writes any part twice."""
    _, out, rows_at_kill, second = shift_run
    assert 30 <= rows_at_kill < N_PARTS, rows_at_kill
    assert second.returncode == 1, second.stderr[-2000:]  # one part is broken
    assert "already in the history" in second.stderr
    db = sqlite3.connect(out / "history.sqlite")
    rows = db.execute("SELECT part_id, status FROM parts").fetchall()
    assert len(rows) == N_PARTS + 1 and len({r[0] for r in rows}) == N_PARTS + 1
    assert sum(r[1] == "ok" for r in rows) == N_PARTS
    summary = json.loads((out / "shift.json").read_text())
    assert summary["batch"]["skipped"] >= rows_at_kill - 1  # a part failed in the first run is tried again
    assert summary["batch"]["processed"] == N_PARTS + 1 - summary["batch"]["skipped"]
    assert [f["part_id"] for f in summary["failed"]] == ["zz_broken"]
    assert "FieldError" in summary["failed"][0]["error"]
    assert sum(1 for _ in (out / "history.csv").open()) == N_PARTS + 2


def test_report_renders_and_names_the_failed_part(shift_run, tmp_path):
    """Fails if the shift report does not load in a browser (broken image, empty table, error text) or does not
    name the failed part."""
    _, out, _, _ = shift_run
    text = check_rendered_report(out / "index.html", tmp_path / "profile", 9, 4, ("Traceback", "NaN", " nan "))
    assert "zz_broken" in text


def test_bad_input_is_refused_with_one_line(tmp_path):
    """Fails if a missing input or a bases path that is not a bases file crashes the verb instead of one error line
    and exit status 2."""
    run = subprocess.run(_command(tmp_path / "nothing_here", tmp_path / "out"), capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2 and run.stderr.strip().count("\n") == 0, run.stderr
    assert "nothing_here" in run.stderr
    (tmp_path / "fields").mkdir()
    (tmp_path / "fields" / "a.vtu").write_text("x")
    (tmp_path / "b.h5").write_text("not hdf5")
    command = _command(tmp_path / "fields", tmp_path / "out")
    command[command.index("--bases") + 1] = str(tmp_path / "b.h5")
    run = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "b.h5" in run.stderr.strip().splitlines()[-1], run.stderr
