"""The results history: one row per inspected part in an embedded SQLite database (stdlib ``sqlite3``), appendable
across shifts, with CSV export for the plant's own tools. The schema is in docs/history_schema.md.

Writing is idempotent per (source, part_id): a part already recorded as processed is never written twice, so a
batch that crashed is rerun with the same database and continues where it stopped (:meth:`History.done` lists what
is there). A part recorded as failed is replaced when a later run processes it. Each part is one transaction: a crash
leaves either the whole part or none of it.

The file states its ``schema_version`` (table ``meta``). Opening a database of another version migrates it when a
migration is known (:data:`MIGRATIONS`: 1 -> 2 adds ``parameters.measured_effect``, 2 -> 3 ``parts.reference`` and
``parts.calibration``) and otherwise refuses it, naming
the version found and the ones this reader reads. A file that is no SQLite database or no hood_decomp history is
refused by name.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import os
import sqlite3
import threading
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hood_decomp.core.method.residual import ResidualAnalysis
from hood_decomp.core.types import BoundaryCorrection, ParameterEstimate
from hood_decomp.errors import HistoryError

SCHEMA_VERSION = 3
#: the note plan_correction puts in a part's ``reason`` for a measured effect (how version 1 recorded it)
_MEASURED_NOTE = " is a measured effect: no boundary to move"
STATUSES = ("ok", "failed")

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE parts (
    id INTEGER PRIMARY KEY,
    source TEXT NOT NULL, part_id TEXT NOT NULL, message INTEGER NOT NULL, stamp_ns INTEGER NOT NULL,
    shift TEXT NOT NULL, status TEXT NOT NULL CHECK (status IN ('ok', 'failed')), error TEXT NOT NULL,
    model_id TEXT NOT NULL, bases_id TEXT NOT NULL, method TEXT NOT NULL,
    coverage REAL, noise_mm REAL, residual_rms_mm REAL, residual_max_mm REAL, residual_mean_mm REAL,
    chi2 REAL, dof INTEGER, p_value REAL, within_model INTEGER, safe_to_apply INTEGER, reason TEXT NOT NULL,
    reference TEXT NOT NULL DEFAULT '', calibration TEXT NOT NULL DEFAULT '',
    UNIQUE (source, part_id)
);
CREATE INDEX parts_time ON parts (stamp_ns, source, message);
CREATE TABLE parameters (
    part INTEGER NOT NULL REFERENCES parts (id) ON DELETE CASCADE, name TEXT NOT NULL,
    value_mm REAL, std_mm REAL, lifted INTEGER NOT NULL, correction_mm REAL,
    measured_effect INTEGER NOT NULL DEFAULT 0, PRIMARY KEY (part, name)
);
CREATE TABLE effects (
    part INTEGER NOT NULL REFERENCES parts (id) ON DELETE CASCADE, name TEXT NOT NULL, share REAL NOT NULL,
    PRIMARY KEY (part, name)
);
CREATE TABLE residuals (
    part INTEGER PRIMARY KEY REFERENCES parts (id) ON DELETE CASCADE, n INTEGER NOT NULL, data BLOB NOT NULL
);
"""
_PART_COLUMNS = ("source", "part_id", "message", "stamp_ns", "shift", "status", "error", "model_id", "bases_id",
                 "calibration", "reference", "method", "coverage", "noise_mm", "residual_rms_mm", "residual_max_mm",
                 "residual_mean_mm", "chi2", "dof", "p_value", "within_model", "safe_to_apply", "reason")


def _migrate_1_to_2(db: sqlite3.Connection) -> None:
    """Version 2 flags measured effects per parameter (``parameters.measured_effect``). Version 1 kept the flag only
    in the part's ``reason``, as plan_correction's note "<name> is a measured effect: no boundary to move": each
    parameter so named there is flagged, every other one is not."""
    db.execute("ALTER TABLE parameters ADD COLUMN measured_effect INTEGER NOT NULL DEFAULT 0")
    flagged = [(part, note[: -len(_MEASURED_NOTE)]) for part, reason in db.execute("SELECT id, reason FROM parts")
               for note in reason.split("; ") if note.endswith(_MEASURED_NOTE)]
    db.executemany("UPDATE parameters SET measured_effect = 1 WHERE part = ? AND name = ?", flagged)


def _migrate_2_to_3(db: sqlite3.Connection) -> None:
    """Version 3 records per part the reference it was estimated against and the bases' calibration
    (``parts.reference``, ``parts.calibration``). Version 2 recorded neither; its parts get "" in both: no reference
    was known to the history then, and its rows cannot say whether one was used."""
    db.execute("ALTER TABLE parts ADD COLUMN reference TEXT NOT NULL DEFAULT ''")
    db.execute("ALTER TABLE parts ADD COLUMN calibration TEXT NOT NULL DEFAULT ''")


#: version found -> function upgrading an open connection by one version
MIGRATIONS: dict[int, Callable[[sqlite3.Connection], None]] = {1: _migrate_1_to_2, 2: _migrate_2_to_3}


@dataclass(frozen=True)
class PartRecord:
    """What the history keeps of one part (mm throughout).

    source: the bag or file it came from; part_id; message: index of the message in the bag (0 for a file);
    stamp_ns: the scan's stamp (ns since the epoch); shift: a label of the run that wrote it. status: "ok" or
    "failed" (then ``error`` says why and the numbers are NaN). calibration: the id of the calibration the bases were
    rebuilt with ("" for uncalibrated bases; io.bases.calibration_id); reference: the reference the field was made
    relative to, as the nodes' messages name it ("cell:PATH" or "part:PATH", the REF.json resolved; "" for none):
    values of parts against different references are not comparable. names, values, std, lifted, corrections,
    measured_effect: (P,) per parameter (measured_effect: True for a parameter without a boundary, whose value is an
    amplitude; empty when the estimate flags none). safe_to_apply, reason: the correction's decision. coverage,
    noise_mm, residual statistics, chi2, dof, p_value, within_model: the one within-model test. effects: (name,
    share) of the decomposition.
    residual: (N,) float32 mm, NaN where unseen, or None (not kept).
    """

    source: str
    part_id: str
    message: int
    stamp_ns: int
    shift: str = ""
    status: str = "ok"
    error: str = ""
    model_id: str = ""
    bases_id: str = ""
    calibration: str = ""
    reference: str = ""
    method: str = ""
    coverage: float = float("nan")
    noise_mm: float = float("nan")
    residual_rms_mm: float = float("nan")
    residual_max_mm: float = float("nan")
    residual_mean_mm: float = float("nan")
    chi2: float = float("nan")
    dof: int = 0
    p_value: float = float("nan")
    within_model: bool = False
    safe_to_apply: bool = False
    reason: str = ""
    names: tuple[str, ...] = ()
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    std: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lifted: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    corrections: np.ndarray = field(default_factory=lambda: np.zeros(0))
    effects: tuple[tuple[str, float], ...] = ()
    residual: np.ndarray | None = None
    measured_effect: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def measured_flags(self) -> np.ndarray:
        """(P,) bool: measured_effect, all False when the record flags none."""
        flags = np.asarray(self.measured_effect, dtype=bool)
        return flags if flags.size else np.zeros(len(self.names), dtype=bool)

    @property
    def key(self) -> tuple[str, str]:
        return (self.source, self.part_id)


@dataclass(frozen=True)
class HistoryTable:
    """Parts of a history in time order (stamp, source, message), M rows, for analysis.

    records: (M,) PartRecord without residuals. names: the parameter labels (union, in first-seen order);
    values, std: (M, P) mm (NaN where a part has no such parameter or failed); lifted: (M, P) bool;
    measured_effect: (P,) bool, True for a label some part flags as a measured effect (a parameter without a
    boundary: its values are amplitudes).
    """

    records: tuple[PartRecord, ...]
    names: tuple[str, ...]
    values: np.ndarray
    std: np.ndarray
    lifted: np.ndarray
    measured_effect: np.ndarray

    @property
    def references(self) -> tuple[str, ...]:
        """(M,) the reference each part was estimated against ("" none): values across different ones are not
        comparable."""
        return tuple(record.reference for record in self.records)

    @property
    def calibrations(self) -> tuple[str, ...]:
        """(M,) the calibration id of each part's bases ("" uncalibrated)."""
        return tuple(record.calibration for record in self.records)


def _none_if_nan(value: float) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)


def bases_file_id(path: str | Path) -> str:
    """Fingerprint of a bases file's bytes (16 hex digits): the ``bases_id`` a history row names."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def inspection_record(base: PartRecord, estimate: ParameterEstimate, analysis: ResidualAnalysis,
                      correction: BoundaryCorrection, effects: tuple[tuple[str, float], ...] = (),
                      keep_residual: bool = True) -> PartRecord:
    """The history row of one inspected part: ``base`` (source, part id, message, stamp, shift, model and bases id,
    calibration, reference, method) completed by its estimate, within-model analysis, correction and decomposition
    ``effects`` (name, share). The one place a result becomes a row: the shift's workers and the estimator node both
    call it."""
    check = estimate.check
    return dataclasses.replace(
        base, status="ok", error="", coverage=float(estimate.coverage), noise_mm=analysis.noise_mm,
        residual_rms_mm=analysis.rms_mm, residual_max_mm=analysis.max_mm, residual_mean_mm=analysis.mean_mm,
        chi2=float("nan") if check is None else check.statistic, dof=0 if check is None else check.dof,
        p_value=analysis.p_value, within_model=analysis.within_model, safe_to_apply=correction.safe_to_apply,
        reason=correction.reason, names=tuple(estimate.names), values=np.asarray(estimate.values, float),
        std=np.asarray(estimate.std, float), lifted=np.asarray(estimate.lifted, bool),
        corrections=np.asarray(correction.corrections, float), effects=tuple(effects),
        measured_effect=np.zeros(0, bool) if estimate.measured_effect is None else np.asarray(
            estimate.measured_effect, bool),
        residual=np.asarray(estimate.residual, np.float32) if keep_residual else None)


class History:
    """An open results history (``with History(path) as history: ...``); creates the file when it does not exist.
    timeout_s: how long a write waits for another writer's lock before it fails (sqlite3.OperationalError)."""

    def __init__(self, path: str | Path, timeout_s: float = 30.0) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s
        self._db: sqlite3.Connection | None = None

    def __enter__(self) -> History:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> History:
        new = not self.path.exists() or self.path.stat().st_size == 0
        if not new and not self.path.is_file():
            raise HistoryError(f"history {self.path} is not a file")
        try:
            if new:
                self._create()
            # any thread may use it (a node's timer and subscription run in different executor threads); the
            # caller serialises its use (HistoryWriter holds a lock)
            self._db = sqlite3.connect(self.path, timeout=self.timeout_s, check_same_thread=False)
            self._db.execute("PRAGMA foreign_keys = ON")
            self._check_version()
        except sqlite3.DatabaseError as error:
            self.close()
            raise HistoryError(f"history {self.path} is not a hood_decomp results history: {error}") from error
        except HistoryError:
            self.close()
            raise
        return self

    def _create(self) -> None:
        """Write the schema to a private file beside ``path`` and only then give it the history's name, so that a
        reader (a live shift report, another writer) never sees a database without its tables. A writer that lost a
        race for the name uses the winner's file; an empty file at ``path`` is replaced."""
        staging = self.path.with_name(f".{self.path.name}.{os.getpid()}.{threading.get_ident()}.new")
        try:
            db = sqlite3.connect(staging)
            try:
                with db:
                    db.executescript(_SCHEMA)
                    db.execute("INSERT INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
                    db.execute("INSERT INTO meta VALUES ('application', 'hood_decomp results history')")
            finally:
                db.close()
            try:
                os.link(staging, self.path)
            except FileExistsError:
                if self.path.stat().st_size == 0:
                    os.replace(staging, self.path)
            except OSError:  # a file system without hard links: no race-free name, but still never half-made
                if not self.path.exists():
                    os.replace(staging, self.path)
        finally:
            staging.unlink(missing_ok=True)

    def _check_version(self) -> None:
        assert self._db is not None
        tables = {row[0] for row in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "meta" not in tables:
            raise HistoryError(f"history {self.path} is an SQLite database without a 'meta' table: not a hood_decomp "
                               "results history")
        row = self._db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        try:
            version = int(row[0])
        except (TypeError, ValueError):
            raise HistoryError(f"history {self.path} states no valid schema_version ({row!r})") from None
        while version != SCHEMA_VERSION:
            if version not in MIGRATIONS:
                raise HistoryError(f"history {self.path} has schema_version {version}; this hood_decomp reads version "
                                   f"{SCHEMA_VERSION} and migrates {sorted(MIGRATIONS) or 'no older one'}")
            with self._db:
                MIGRATIONS[version](self._db)
                version += 1
                self._db.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(version),))

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None

    @property
    def db(self) -> sqlite3.Connection:
        if self._db is None:
            raise HistoryError(f"history {self.path} is not open")
        return self._db

    def done(self) -> set[tuple[str, str]]:
        """(source, part_id) of every part recorded as processed ("ok")."""
        return {(s, p) for s, p in self.db.execute("SELECT source, part_id FROM parts WHERE status = 'ok'")}

    def add(self, record: PartRecord) -> bool:
        """Record one part in one transaction; False (nothing written) when it is recorded as processed already."""
        if record.status not in STATUSES:
            raise HistoryError(f"part status must be one of {STATUSES}, got {record.status!r}")
        n = len(record.names)
        if not (len(record.values) == len(record.std) == len(record.lifted) == len(record.corrections) == n
                and len(record.measured_effect) in (0, n)):
            raise HistoryError(f"part {record.part_id}: {n} names but {len(record.values)} values, {len(record.std)} "
                               f"std, {len(record.lifted)} lifted flags, {len(record.corrections)} corrections, "
                               f"{len(record.measured_effect)} measured-effect flags")
        db = self.db
        with db:
            row = db.execute("SELECT id, status FROM parts WHERE source = ? AND part_id = ?", record.key).fetchone()
            if row is not None:
                if row[1] == "ok":
                    return False
                db.execute("DELETE FROM parts WHERE id = ?", (row[0],))
            values = [getattr(record, c) for c in _PART_COLUMNS]
            values = [_none_if_nan(v) if isinstance(v, float) else (int(v) if isinstance(v, bool | np.bool_) else v)
                      for v in values]
            cursor = db.execute(f"INSERT INTO parts ({', '.join(_PART_COLUMNS)}) VALUES "
                                f"({', '.join('?' * len(_PART_COLUMNS))})", values)
            part = cursor.lastrowid
            db.executemany("INSERT INTO parameters VALUES (?, ?, ?, ?, ?, ?, ?)", [
                (part, name, _none_if_nan(v), _none_if_nan(s), int(lifted), _none_if_nan(c), int(measured))
                for name, v, s, lifted, c, measured in zip(record.names, record.values, record.std, record.lifted,
                                                           record.corrections, record.measured_flags(), strict=True)])
            db.executemany("INSERT INTO effects VALUES (?, ?, ?)", [(part, n_, float(s)) for n_, s in record.effects])
            if record.residual is not None:
                data = np.asarray(record.residual, dtype="<f4")
                db.execute("INSERT INTO residuals VALUES (?, ?, ?)", (part, int(data.size), data.tobytes()))
        return True

    def extend(self, records: Iterable[PartRecord]) -> int:
        """Record several parts (each its own transaction); the number newly written."""
        return sum(self.add(record) for record in records)

    def _records(self, where: str = "", args: Sequence[object] = ()) -> list[tuple[int, PartRecord]]:
        db = self.db
        rows = db.execute(f"SELECT id, {', '.join(_PART_COLUMNS)} FROM parts {where} "
                          "ORDER BY stamp_ns, source, message, part_id", args).fetchall()
        parameters: dict[int, list[tuple]] = {}
        for part, *rest in db.execute("SELECT part, name, value_mm, std_mm, lifted, correction_mm, measured_effect "
                                      "FROM parameters ORDER BY part, rowid"):
            parameters.setdefault(part, []).append(tuple(rest))
        effects: dict[int, list[tuple[str, float]]] = {}
        for part, name, share in db.execute("SELECT part, name, share FROM effects ORDER BY part, rowid"):
            effects.setdefault(part, []).append((name, share))
        out = []
        for row in rows:
            part = row[0]
            raw = dict(zip(_PART_COLUMNS, row[1:], strict=True))
            for key in ("coverage", "noise_mm", "residual_rms_mm", "residual_max_mm", "residual_mean_mm", "chi2",
                        "p_value"):
                raw[key] = float("nan") if raw[key] is None else float(raw[key])
            raw["dof"] = int(raw["dof"] or 0)
            raw["within_model"], raw["safe_to_apply"] = bool(raw["within_model"]), bool(raw["safe_to_apply"])
            params = parameters.get(part, [])
            numbers = np.array([[np.nan if x is None else x for x in (p[1], p[2], p[4])] for p in params],
                               dtype=float).reshape(-1, 3)
            out.append((part, PartRecord(
                **raw, names=tuple(p[0] for p in params), values=numbers[:, 0], std=numbers[:, 1],
                lifted=np.array([bool(p[3]) for p in params], dtype=bool), corrections=numbers[:, 2],
                effects=tuple(effects.get(part, [])), measured_effect=np.array([bool(p[5]) for p in params],
                                                                               dtype=bool))))
        return out

    def records(self) -> list[PartRecord]:
        """Every part in time order (stamp, source, message), without residuals."""
        return [record for _, record in self._records()]

    def table(self) -> HistoryTable:
        """Every part in time order as arrays (:class:`HistoryTable`)."""
        records = self.records()
        names: list[str] = []
        for record in records:
            names.extend(n for n in record.names if n not in names)
        values = np.full((len(records), len(names)), np.nan)
        std = np.full_like(values, np.nan)
        lifted = np.zeros(values.shape, dtype=bool)
        measured = np.zeros(len(names), dtype=bool)
        for i, record in enumerate(records):
            columns = [names.index(n) for n in record.names]
            values[i, columns], std[i, columns], lifted[i, columns] = record.values, record.std, record.lifted
            measured[columns] |= record.measured_flags()
        return HistoryTable(tuple(records), tuple(names), values, std, lifted, measured)

    def residuals(self, keys: Sequence[tuple[str, str]]) -> np.ndarray:
        """Residual fields (len(keys), N) mm of the given (source, part_id), NaN where unseen; HistoryError for a part
        without a stored residual or residuals of different lengths."""
        out = []
        for key in keys:
            row = self.db.execute("SELECT r.n, r.data FROM residuals r JOIN parts p ON p.id = r.part "
                                  "WHERE p.source = ? AND p.part_id = ?", key).fetchone()
            if row is None:
                raise HistoryError(f"history {self.path} holds no residual of part {key[1]!r} from {key[0]}")
            data = np.frombuffer(row[1], dtype="<f4")
            if data.size != row[0]:
                raise HistoryError(f"residual of part {key[1]!r} has {data.size} values, its row states {row[0]}")
            out.append(data.astype(float))
        if len({r.size for r in out}) > 1:
            raise HistoryError("the residuals have different lengths: the parts come from different models")
        return np.array(out).reshape(len(out), -1)

    def export_csv(self, path: str | Path) -> Path:
        """All parts as one CSV table (one row per part, time order): the part columns, then per parameter
        ``<name>_mm``, ``<name>_std_mm``, ``<name>_lifted``, ``<name>_correction_mm``, ``<name>_measured_effect``,
        then ``share_<effect>``."""
        records = self.records()
        names: list[str] = []
        effects: list[str] = []
        for record in records:
            names.extend(n for n in record.names if n not in names)
            effects.extend(n for n, _ in record.effects if n not in effects)
        header = [*_PART_COLUMNS, *[f"{n}{s}" for n in names
                                    for s in ("_mm", "_std_mm", "_lifted", "_correction_mm", "_measured_effect")],
                  *[f"share_{e}" for e in effects]]
        path = Path(path)
        with path.open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(header)
            for record in records:
                by_name = {n: (v, s, int(lifted), c, int(m)) for n, v, s, lifted, c, m in
                           zip(record.names, record.values, record.std, record.lifted, record.corrections,
                               record.measured_flags(), strict=True)}
                shares = dict(record.effects)
                row = [_csv_value(getattr(record, c)) for c in _PART_COLUMNS]
                for name in names:
                    row.extend(_csv_value(x) for x in by_name.get(name, ("", "", "", "", "")))
                row.extend(_csv_value(shares.get(e, "")) for e in effects)
                writer.writerow(row)
        return path


class HistoryWriter:
    """Appends records to the history at ``path`` as they come (the estimator node's live history), never losing
    one to a database that cannot be written for a while: a record that could not be written (a locked database, a
    path that is not writable, a file that is no history) stays pending and is written, oldest first, by the next
    :meth:`append` or :meth:`flush` that succeeds. At most ``max_pending`` records wait; beyond that the oldest are
    dropped and counted in ``dropped`` (a bounded memory for a database that never comes back).
    timeout_s: how long one write waits for another writer's lock. Thread-safe: one lock serialises every call
    (a node's timer and its subscription run in different executor threads)."""

    def __init__(self, path: str | Path, timeout_s: float = 0.5, max_pending: int = 1000) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s
        self.pending: deque[PartRecord] = deque()
        self.max_pending = max_pending
        self.written = 0
        self.dropped = 0
        self._history: History | None = None
        self._lock = threading.RLock()

    def append(self, record: PartRecord) -> str:
        """Queue ``record`` and write everything pending; "" when all is written, else why not (one line)."""
        with self._lock:
            self.pending.append(record)
            while len(self.pending) > self.max_pending:
                self.pending.popleft()
                self.dropped += 1
            return self.flush()

    def flush(self) -> str:
        """Write every pending record; "" when all is written, else why not (the rest stays pending)."""
        with self._lock:
            return self._flush()

    def _flush(self) -> str:
        try:
            if self._history is None:
                self._history = History(self.path, self.timeout_s).open()
            while self.pending:
                self._history.add(self.pending[0])  # a part written before (a rerun) is not written twice
                self.pending.popleft()
                self.written += 1
        except (HistoryError, sqlite3.Error, OSError) as error:
            self.close()  # reopened at the next attempt: the file may have been replaced or fixed
            return f"history {self.path} not written ({len(self.pending)} parts pending): {error}"
        return ""

    def close(self) -> None:
        with self._lock:
            if self._history is not None:
                self._history.close()
                self._history = None


def _csv_value(value: object) -> object:
    if isinstance(value, bool | np.bool_):
        return int(value)
    if isinstance(value, float | np.floating):
        return "" if not np.isfinite(value) else repr(float(value))
    return value
