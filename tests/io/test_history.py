"""The results history (hood_decomp.io.history) on real SQLite files: round trip, idempotent writes, schema version,
refusal of foreign files, CSV export read back with the csv module."""

from __future__ import annotations

import csv
import dataclasses
import sqlite3
import threading

import numpy as np
import pytest

from hood_decomp.errors import HistoryError
from hood_decomp.io.history import History, HistoryWriter, PartRecord


def _record(i: int, source: str = "bag_a", status: str = "ok", n: int = 5) -> PartRecord:
    rng = np.random.default_rng(i)
    residual = rng.normal(0, 0.02, n)
    residual[0] = np.nan
    return PartRecord(
        source=source, part_id=f"p{i}", message=i, stamp_ns=1_000 + 10 * i, shift="s1", status=status,
        error="" if status == "ok" else "boom", model_id="m", bases_id="b", method="contact", coverage=0.9,
        noise_mm=0.02, residual_rms_mm=0.02 + i, residual_max_mm=0.05, residual_mean_mm=0.0, chi2=12.0, dof=7,
        p_value=0.1, within_model=i % 2 == 0, safe_to_apply=i % 3 == 0, reason="r",
        names=("A", "B"), values=np.array([0.1 * i, -0.2]), std=np.array([0.01, np.nan]),
        lifted=np.array([False, True]), corrections=np.array([-0.1 * i, 0.0]), effects=(("A", 0.7), ("B", 0.3)),
        residual=residual.astype(np.float32),
    )


def test_round_trip_in_time_order(tmp_path):
    """Fails if a stored value (numbers, NaN std, flags, effects, residual with NaN) does not come back as written, or
    if parts are not returned in time order."""
    path = tmp_path / "h.sqlite"
    with History(path) as history:
        assert history.extend([_record(3), _record(1), _record(2)]) == 3
    with History(path) as history:
        records = history.records()
        table = history.table()
        residuals = history.residuals([("bag_a", "p3"), ("bag_a", "p1")])
    assert [r.part_id for r in records] == ["p1", "p2", "p3"]
    third = records[2]
    assert third.values[0] == pytest.approx(0.3) and np.isnan(third.std[1]) and third.lifted.tolist() == [False, True]
    assert third.effects == (("A", 0.7), ("B", 0.3)) and third.residual_rms_mm == pytest.approx(3.02)
    assert third.within_model is False and third.safe_to_apply is True
    assert table.names == ("A", "B") and table.values[:, 0] == pytest.approx([0.1, 0.2, 0.3])
    np.testing.assert_allclose(residuals[0], _record(3).residual, rtol=1e-7)
    assert np.isnan(residuals[1, 0])


def test_writes_are_idempotent_and_failed_parts_are_replaced(tmp_path):
    """Fails if writing a processed part again adds a row, or if a part recorded as failed cannot be replaced by a
    later successful run."""
    path = tmp_path / "h.sqlite"
    with History(path) as history:
        assert history.add(_record(1)) and history.add(_record(2, status="failed"))
        assert not history.add(_record(1))
        assert history.done() == {("bag_a", "p1")}
        assert history.add(_record(2))
        assert history.done() == {("bag_a", "p1"), ("bag_a", "p2")}
        assert history.add(_record(1, source="bag_b"))
    db = sqlite3.connect(path)
    assert db.execute("SELECT COUNT(*) FROM parts").fetchone()[0] == 3
    assert db.execute("SELECT COUNT(*) FROM parameters").fetchone()[0] == 6
    assert db.execute("SELECT COUNT(*) FROM residuals").fetchone()[0] == 3


def test_unknown_schema_and_foreign_files_are_refused(tmp_path):
    """Fails if a history of another schema version, an SQLite file of another application or a non-database file is
    opened instead of refused by name."""
    path = tmp_path / "h.sqlite"
    History(path).open().close()
    db = sqlite3.connect(path)
    with db:
        db.execute("UPDATE meta SET value = '7' WHERE key = 'schema_version'")
    db.close()
    with pytest.raises(HistoryError, match="schema_version 7"):
        History(path).open()
    other = tmp_path / "other.sqlite"
    sqlite3.connect(other).execute("CREATE TABLE t (x)").connection.close()
    with pytest.raises(HistoryError, match="not a hood_decomp results history"):
        History(other).open()
    text = tmp_path / "notes.sqlite"
    text.write_text("this is not a database\n" * 50)
    with pytest.raises(HistoryError, match="not a hood_decomp results history"):
        History(text).open()


def test_csv_export(tmp_path):
    """Fails if the CSV lacks a part, a parameter column or an effect share, or writes NaN instead of an empty cell."""
    path = tmp_path / "h.sqlite"
    with History(path) as history:
        history.extend([_record(1), _record(2)])
        out = history.export_csv(tmp_path / "h.csv")
    rows = list(csv.DictReader(out.open()))
    assert [r["part_id"] for r in rows] == ["p1", "p2"]
    assert float(rows[1]["A_mm"]) == pytest.approx(0.2) and rows[1]["B_std_mm"] == ""
    assert rows[0]["B_lifted"] == "1" and float(rows[0]["share_A"]) == pytest.approx(0.7)
    assert rows[0]["within_model"] == "0" and rows[1]["within_model"] == "1"


def test_writer_keeps_parts_through_a_lock_and_a_bad_path(tmp_path):
    """Fails if the live writer (the estimator node's) loses a part while the database is locked by another
    connection or its path cannot be opened, writes a part twice, reports no reason, cannot be flushed from another
    thread, or keeps more than max_pending parts without counting the dropped ones."""
    path = tmp_path / "live.sqlite"
    writer = HistoryWriter(path, timeout_s=0.05)
    assert writer.append(_record(1)) == "" and writer.written == 1
    lock = sqlite3.connect(path, isolation_level=None)
    lock.execute("BEGIN EXCLUSIVE")
    problem = writer.append(_record(2))
    assert "locked" in problem and "1 parts pending" in problem
    lock.execute("COMMIT")
    lock.close()
    assert writer.append(_record(3)) == "" and not writer.pending
    # the node's retry timer runs in another executor thread than its subscription: the same open writer must work
    # there (a connection bound to its creating thread raised ProgrammingError and killed the timer)
    writer.pending.append(_record(4))
    answers: list[str] = []
    worker = threading.Thread(target=lambda: answers.append(writer.flush()))
    worker.start()
    worker.join(30)
    assert answers == [""]
    with History(path) as history:
        assert [r.part_id for r in history.records()] == ["p1", "p2", "p3", "p4"]

    directory = tmp_path / "a_directory"
    directory.mkdir()
    bad = HistoryWriter(directory, max_pending=2)
    for i in range(4):
        assert "is not a file" in bad.append(_record(10 + i))
    assert [r.part_id for r in bad.pending] == ["p12", "p13"] and bad.dropped == 2
    bad.path = tmp_path / "later.sqlite"  # the path fixed (the node's parameter set anew)
    assert bad.flush() == ""
    with History(bad.path) as history:
        assert [r.part_id for r in history.records()] == ["p12", "p13"]


def test_a_new_history_never_shows_a_file_without_its_tables(tmp_path):
    """Fails if creating a history exposes the file before its schema is in it (a live shift report polling the
    node's history then finds a database without tables), if writers racing to create the same history do not all
    end up in one valid file, or if the private staging files are left behind."""
    path = tmp_path / "live.sqlite"
    seen: list[set[str]] = []
    stop = threading.Event()
    looked = threading.Event()

    def watch() -> None:
        while not stop.is_set():
            if not path.exists():
                continue
            try:
                db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=1)
                try:
                    seen.append({row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")})
                    looked.set()
                finally:
                    db.close()
            except sqlite3.OperationalError:  # the file went between exists() and open: the loop unlinks it
                pass

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        for _ in range(40):
            looked.clear()
            History(path).open().close()
            looked.wait(5.0)  # on a loaded machine the watcher may not run between a creation and its unlink
            path.unlink()
    finally:
        stop.set()
        watcher.join(30)
    assert seen, "the watcher never saw a history"
    schema = {"meta", "parts", "parameters", "effects", "residuals"}
    half_made = [tables for tables in seen if tables != schema]
    assert not half_made, f"{len(half_made)} of {len(seen)} looks saw a history without all its tables: {half_made[0]}"

    barrier = threading.Barrier(4)
    errors: list[BaseException] = []

    def create(i: int) -> None:
        barrier.wait()
        try:
            with History(path) as history:
                history.add(_record(i))
        except BaseException as error:  # the test reports every writer's failure
            errors.append(error)

    writers = [threading.Thread(target=create, args=(i,)) for i in range(4)]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join(30)
    assert not errors
    with History(path) as history:
        assert sorted(r.part_id for r in history.records()) == ["p0", "p1", "p2", "p3"]
        assert history.db.execute("SELECT COUNT(*) FROM meta WHERE key = 'schema_version'").fetchone() == (1,)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["live.sqlite"]


#: schema version 1 as it was released (cef4121): the file format an older history on disk has
_SCHEMA_V1 = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE parts (
    id INTEGER PRIMARY KEY,
    source TEXT NOT NULL, part_id TEXT NOT NULL, message INTEGER NOT NULL, stamp_ns INTEGER NOT NULL,
    shift TEXT NOT NULL, status TEXT NOT NULL CHECK (status IN ('ok', 'failed')), error TEXT NOT NULL,
    model_id TEXT NOT NULL, bases_id TEXT NOT NULL, method TEXT NOT NULL,
    coverage REAL, noise_mm REAL, residual_rms_mm REAL, residual_max_mm REAL, residual_mean_mm REAL,
    chi2 REAL, dof INTEGER, p_value REAL, within_model INTEGER, safe_to_apply INTEGER, reason TEXT NOT NULL,
    UNIQUE (source, part_id)
);
CREATE INDEX parts_time ON parts (stamp_ns, source, message);
CREATE TABLE parameters (
    part INTEGER NOT NULL REFERENCES parts (id) ON DELETE CASCADE, name TEXT NOT NULL,
    value_mm REAL, std_mm REAL, lifted INTEGER NOT NULL, correction_mm REAL, PRIMARY KEY (part, name)
);
CREATE TABLE effects (
    part INTEGER NOT NULL REFERENCES parts (id) ON DELETE CASCADE, name TEXT NOT NULL, share REAL NOT NULL,
    PRIMARY KEY (part, name)
);
CREATE TABLE residuals (
    part INTEGER PRIMARY KEY REFERENCES parts (id) ON DELETE CASCADE, n INTEGER NOT NULL, data BLOB NOT NULL
);
INSERT INTO meta VALUES ('schema_version', '1'), ('application', 'hood_decomp results history');
"""


def test_measured_effect_flags_round_trip_and_export(tmp_path):
    """Fails if a parameter's measured-effect flag is not stored per part and parameter, comes back changed, is lost
    from the table (a label some part flags is a measured effect) or the CSV, if a record without flags does not
    read as all boundaries, or if flags of the wrong length are written instead of refused."""
    path = tmp_path / "h.sqlite"
    flagged = dataclasses.replace(_record(1), measured_effect=np.array([False, True]))
    with History(path) as history:
        history.extend([flagged, _record(2)])
        with pytest.raises(HistoryError, match="1 measured-effect flags"):
            history.add(dataclasses.replace(_record(3), measured_effect=np.array([True])))
        records, table = history.records(), history.table()
        out = history.export_csv(tmp_path / "h.csv")
    assert records[0].measured_effect.tolist() == [False, True]
    assert records[1].measured_effect.tolist() == [False, False]
    assert table.measured_effect.tolist() == [False, True]
    rows = sqlite3.connect(path).execute("SELECT p.part_id, q.name FROM parameters q JOIN parts p ON p.id = q.part "
                                         "WHERE q.measured_effect = 1").fetchall()
    assert rows == [("p1", "B")]
    csv_rows = list(csv.DictReader(out.open()))
    assert [(r["A_measured_effect"], r["B_measured_effect"]) for r in csv_rows] == [("0", "1"), ("0", "0")]


def test_a_version_1_history_is_migrated(tmp_path):
    """Fails if a history written with schema version 1 (created here from its released DDL, not by the code under
    test) does not open, keeps its old version, loses a row or a value, does not flag as measured effects exactly
    the parameters its parts' correction notes named so (a lifted note or a similar name must not flag), cannot take
    a new part afterwards, or writes a processed part twice."""
    path = tmp_path / "old.sqlite"
    db = sqlite3.connect(path)
    db.executescript(_SCHEMA_V1)
    columns = "source, part_id, message, stamp_ns, shift, status, error, model_id, bases_id, method, reason"
    reasons = ("B lifted: commanded position not observable, not corrected; measured_1 is a measured effect: no "
               "boundary to move", "A uncertainty 0.009 mm above 0.0045 mm")
    for part, reason in enumerate(reasons, start=1):
        db.execute(f"INSERT INTO parts ({columns}) VALUES ('bag', 'p{part}', {part}, {part}, 's', 'ok', '', 'm', "
                   f"'b', 'contact', ?)", (reason,))
        db.executemany("INSERT INTO parameters VALUES (?, ?, ?, ?, ?, ?)", [
            (part, "A", 0.1 * part, 0.01, 0, -0.1 * part), (part, "B", -0.2, None, 1, 0.0),
            (part, "measured_1", 0.15, 0.01, 0, 0.0), (part, "measured_10", 0.02, 0.01, 0, 0.0)])
    db.commit()
    db.close()
    with History(path) as history:
        version = history.db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0]
        records = history.records()
        assert history.add(dataclasses.replace(_record(3), measured_effect=np.array([True, False])))
        assert not history.add(_record(3))
        table = history.table()
    assert version == "3"  # through version 2
    assert [r.part_id for r in records] == ["p1", "p2"]
    assert [(r.reference, r.calibration) for r in records] == [("", ""), ("", "")]
    assert records[0].names == ("A", "B", "measured_1", "measured_10")
    assert records[0].values == pytest.approx([0.1, -0.2, 0.15, 0.02]) and records[1].lifted.tolist()[1]
    assert records[0].measured_effect.tolist() == [False, False, True, False]
    assert records[1].measured_effect.tolist() == [False, False, False, False]
    assert table.names == ("A", "B", "measured_1", "measured_10")
    assert table.measured_effect.tolist() == [True, False, True, False]  # p3 flags A
    with History(path) as history:  # opened again: already version 3, nothing migrated twice
        assert len(history.records()) == 3


#: schema version 2 as it was released (80feb13): version 1 with parameters.measured_effect
_SCHEMA_V2 = _SCHEMA_V1.replace(
    "correction_mm REAL, PRIMARY KEY",
    "correction_mm REAL,\n    measured_effect INTEGER NOT NULL DEFAULT 0, PRIMARY KEY",
).replace("('schema_version', '1')", "('schema_version', '2')")


def test_a_version_2_history_is_migrated_with_no_reference_and_no_calibration(tmp_path):
    """Fails if a history written with schema version 2 (made here from its released DDL by SQL text, not by the code
    under test) does not open, keeps version 2, loses a row, a value or a measured-effect flag, gives its parts
    anything but "" as reference and calibration (nothing was recorded then), cannot take a part estimated against a
    reference with calibrated bases afterwards, or loses those two from the CSV."""
    assert "measured_effect" in _SCHEMA_V2 and "'2'" in _SCHEMA_V2
    path = tmp_path / "v2.sqlite"
    db = sqlite3.connect(path)
    db.executescript(_SCHEMA_V2)
    columns = "source, part_id, message, stamp_ns, shift, status, error, model_id, bases_id, method, reason"
    for part in (1, 2):
        db.execute(f"INSERT INTO parts ({columns}) VALUES ('bag', 'p{part}', {part}, {part}, 's', 'ok', '', 'm', "
                   "'b', 'contact', '')")
        db.executemany("INSERT INTO parameters VALUES (?, ?, ?, ?, ?, ?, ?)", [
            (part, "A", 0.1 * part, 0.01, 0, -0.1 * part, 0), (part, "measured_1", 0.15, 0.01, 0, 0.0, 1)])
    db.commit()
    db.close()
    new = dataclasses.replace(_record(3), reference="cell:/cell/ref.json", calibration="0123456789abcdef")
    with History(path) as history:
        version = history.db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0]
        old = history.records()
        assert history.add(new)
        table = history.table()
        out = history.export_csv(tmp_path / "h.csv")
    assert version == "3"
    assert [(r.part_id, r.reference, r.calibration) for r in old] == [("p1", "", ""), ("p2", "", "")]
    assert old[1].values == pytest.approx([0.2, 0.15]) and old[1].measured_effect.tolist() == [False, True]
    assert table.references == ("", "", "cell:/cell/ref.json")
    assert table.calibrations == ("", "", "0123456789abcdef")
    raw = sqlite3.connect(path).execute("SELECT part_id, reference, calibration FROM parts ORDER BY id").fetchall()
    assert raw == [("p1", "", ""), ("p2", "", ""), ("p3", "cell:/cell/ref.json", "0123456789abcdef")]
    rows = list(csv.DictReader(out.open()))
    assert [(r["reference"], r["calibration"]) for r in rows] == [("", ""), ("", ""),
                                                                  ("cell:/cell/ref.json", "0123456789abcdef")]
    with History(path) as history:  # opened again: nothing migrated twice
        assert len(history.records()) == 3


def test_reference_and_calibration_round_trip_on_a_new_history(tmp_path):
    """Fails if a part's reference or calibration is not stored as written, comes back changed or swapped, or a part
    recorded without them does not read as "" (no reference, uncalibrated)."""
    path = tmp_path / "h.sqlite"
    parts = [dataclasses.replace(_record(1), reference="part:/a/ref one.json", calibration="c1"), _record(2),
             dataclasses.replace(_record(3), reference="cell:/b/ref.json")]
    with History(path) as history:
        history.extend(parts)
    with History(path) as history:
        records = history.records()
    assert [(r.reference, r.calibration) for r in records] == [("part:/a/ref one.json", "c1"), ("", ""),
                                                               ("cell:/b/ref.json", "")]
