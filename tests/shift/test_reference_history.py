"""`hood-decomp shift --reference REF.json` (issue 16): every part is estimated against the cell's reference, the
results history records that reference and the bases' calibration per part, and a shift whose parts were estimated
against different references says so in its report (their values are not comparable)."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sqlite3
import subprocess
import sys

import pytest

from tests.hood20 import hood20
from tests.shift.conftest import write_fields

N_PARTS = 6
LOCK_L = 0.25  # the reference's stated setting: the part that is its own reference must come out there


def _shift(inputs, out, history, reference):
    command = [sys.executable, "-m", "hood_decomp.cli", "shift", *map(str, inputs), "--bases",
               str(hood20().bases_path), "--out", str(out), "--history", str(history), "--workers", "1",
               "--reference", str(reference)]
    return subprocess.run(command, capture_output=True, text=True, timeout=600)


def _reference(directory, field, setting):
    """REF.json in ``directory`` naming a copy of ``field`` with its known ``setting``."""
    directory.mkdir(parents=True)
    shutil.copy(field, directory / "ref.vtu")
    (directory / "ref.json").write_text(json.dumps({"field": "ref.vtu", "setting": setting}))
    return directory / "ref.json"


@pytest.fixture(scope="module")
def two_shifts(tmp_path_factory):
    """Shift 1: parts A against reference R1 (a copy of A's first part at LOCK_L = 0.25 mm). Shift 2, into the same
    history: A again (already recorded, not processed again) and parts B, against reference R2 (all zero setting)."""
    root = tmp_path_factory.mktemp("reference_shift")
    a = write_fields(root / "a", N_PARTS, seed=3)
    b = write_fields(root / "b", N_PARTS, seed=4)
    own = sorted(a.glob("*.vtu"))[0]
    r1 = _reference(root / "cell1", own, {"LOCK_L": LOCK_L})
    r2 = _reference(root / "cell2", sorted(b.glob("*.vtu"))[0], {})
    history = root / "history.sqlite"
    first = _shift([a], root / "out1", history, r1)
    second = _shift([a, b], root / "out2", history, r2)
    return root, own, r1, r2, history, first, second


def test_each_part_records_the_reference_it_was_estimated_against(two_shifts):
    """Fails if a part's history row does not name the reference its estimate used ("cell:" and the REF.json
    resolved, as the nodes' messages name it), if the part of the second shift already recorded against R1 is
    rewritten with R2, if the bases' calibration is not "" for these uncalibrated bases, or if the reference was only
    named and not used: the part that is R1's own field must estimate LOCK_L at R1's stated setting (0.25 mm; the
    reference-relative field is then the model's own field at that setting), not at its measured value."""
    _, own, r1, r2, history, first, second = two_shifts
    assert first.returncode == 0, first.stderr[-2000:]
    assert second.returncode == 0, second.stderr[-2000:]
    db = sqlite3.connect(history)
    rows = db.execute("SELECT source, part_id, reference, calibration, status FROM parts").fetchall()
    assert len(rows) == 2 * N_PARTS and all(r[4] == "ok" for r in rows)
    by_dir = {(r[0].split("/")[-2], r[2], r[3]) for r in rows}
    assert by_dir == {("a", f"cell:{r1.resolve()}", ""), ("b", f"cell:{r2.resolve()}", "")}, by_dir
    value = db.execute("SELECT q.value_mm FROM parameters q JOIN parts p ON p.id = q.part WHERE p.part_id = ? AND "
                       "q.name = 'LOCK_L'", (own.stem,)).fetchone()[0]
    assert value == pytest.approx(LOCK_L, abs=1e-3)
    measured = db.execute("SELECT COUNT(*) FROM parts WHERE reference = ''").fetchone()[0]
    assert measured == 0


def test_a_shift_mixing_references_says_so_in_its_report(two_shifts):
    """Fails if the report of the second shift (parts against R1 and against R2) does not list both references with
    their part counts and warn that values across them are not comparable (page and shift.json), or if the first
    shift (one reference) warns although its parts share one."""
    root, _, r1, r2, _, first, second = two_shifts
    assert first.returncode == 0 and second.returncode == 0, second.stderr[-2000:]
    page = (root / "out2" / "index.html").read_text()
    assert f"cell:{r1.resolve()}" in page and f"cell:{r2.resolve()}" in page
    assert "mixes 2 references" in page and "not comparable" in page
    numbers = json.loads((root / "out2" / "shift.json").read_text())
    assert sorted((g["reference"], g["parts"]) for g in numbers["references"]) == sorted(
        [(f"cell:{r1.resolve()}", N_PARTS), (f"cell:{r2.resolve()}", N_PARTS)])
    assert "not comparable" in numbers["references_note"]
    single = (root / "out1" / "index.html").read_text()
    assert f"cell:{r1.resolve()}" in single and "mixes" not in single
    assert json.loads((root / "out1" / "shift.json").read_text())["references_note"] == ""
    rows = (root / "out2" / "history.csv").read_text().splitlines()
    assert "reference" in rows[0].split(",") and sum(str(r2.resolve()) in row for row in rows) == N_PARTS


def test_a_reference_that_does_not_serve_the_bases_is_refused_before_the_batch(tmp_path):
    """Fails if a reference naming a parameter the bases lack is accepted (every part would then fail in the batch)
    instead of refused with one line and exit status 2 before any part is processed."""
    fields = write_fields(tmp_path / "parts", 2, seed=5)
    reference = _reference(tmp_path / "cell", sorted(fields.glob("*.vtu"))[0], {"LOCK_Z": 0.1})
    run = _shift([fields], tmp_path / "out", tmp_path / "h.sqlite", reference)
    assert run.returncode == 2, run.stderr[-2000:]
    assert run.stderr.strip().count("\n") == 0 and "LOCK_Z" in run.stderr, run.stderr
    assert not (tmp_path / "h.sqlite").exists()


def test_a_part_of_calibrated_bases_records_the_calibration_and_the_reference(tmp_path):
    """Fails if the worker's record of a part (process_task, what every shift row comes from) does not carry the id of
    the calibration its bases were rebuilt with (written into the bases file here: "cal-0123") and the reference its
    field was made relative to, or loses either on the way through a real SQLite history; or if a part of the same
    bases without a reference does not record "" as its reference."""
    from hood_decomp.io.bases import save_bases
    from hood_decomp.io.history import History
    from hood_decomp.shift.part import Options, PartTask, process_task

    record = json.dumps({"id": "cal-0123", "entries": [{"name": "ref.vtu", "loo_rms_mm": 0.02}], "loo_rms_mm": 0.02})
    bases_path = tmp_path / "calibrated.h5"
    save_bases(bases_path, dataclasses.replace(hood20().bases, calibration=record))
    fields = sorted(write_fields(tmp_path / "parts", 2, seed=6).glob("*.vtu"))
    reference = _reference(tmp_path / "cell", fields[0], {"LOCK_L": LOCK_L})
    tasks = [PartTask(str(path), path.stem, 0, i, "field", str(path)) for i, path in enumerate(fields)]
    against = process_task(tasks[0], str(bases_path), Options(reference=str(reference.resolve())))
    without = process_task(tasks[1], str(bases_path), Options())
    assert against.status == without.status == "ok", (against.error, without.error)
    with History(tmp_path / "h.sqlite") as history:
        history.extend([against, without])
        back = {r.part_id: r for r in history.records()}
    assert (back[fields[0].stem].reference, back[fields[0].stem].calibration) == (f"cell:{reference.resolve()}",
                                                                                  "cal-0123")
    assert (back[fields[1].stem].reference, back[fields[1].stem].calibration) == ("", "cal-0123")
    lock_l = back[fields[0].stem].values[list(back[fields[0].stem].names).index("LOCK_L")]
    assert lock_l == pytest.approx(LOCK_L, abs=1e-3)  # the reference was used, not only named
