"""Calibration files (CAL.json) and reference files (REF.json): fields or scans of the part in known settings.

CAL.json is a JSON list of entries; REF.json is one entry (or a list of one). An entry is

    {"field": "ref.vtu", "setting": {"HINGE_X": 0.5}}          a field file, or
    {"scans": ["ref.ply"], "setting": {...}}                   one scan (a multi-view entry with "poses" needs the
                                                               multi-view fusion of issue 17: refused until then)

with the setting in mm per parameter label (unset parameters are 0). Optional "name" (how messages call the entry;
default: its file). File names are relative to the JSON file's directory and must stay inside it (no absolute path,
no ".." out of it, resolved through links): a calibration file cannot make the program read any other file.

:func:`read_reference` reads a REF.json for a set of bases and prepares it once (:class:`Reference`): what the CLI's
``--reference`` and the estimator and decomposition nodes' ``reference`` parameter and ``set_reference`` service use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hood_decomp.core.types import DisplacementField, SkinSurface
from hood_decomp.errors import CalibrationError, HoodDecompError
from hood_decomp.io.json_values import loads_strict
from hood_decomp.io.small_files import read_small_file

if TYPE_CHECKING:  # only named in annotations: the module stays light for the CLI's start-up
    from hood_decomp.core.loop.calibration import ReferenceOffset
    from hood_decomp.core.method.bases import Bases

#: largest calibration file (bytes) read: a list of entries, not data
MAX_BYTES = 1 << 20
#: most entries one calibration reads
MAX_ENTRIES = 1000
ENTRY_KEYS = {"field", "scans", "poses", "setting", "name"}


@dataclass(frozen=True)
class FieldEntry:
    """One entry read: its name, field (N,) mm, setting label -> mm and its field's or scan's :func:`file_key`
    (taken before reading it)."""

    name: str
    field: DisplacementField
    setting: dict[str, float]
    source: tuple[str, int, int]

    def setting_vector(self, names: tuple[str, ...]) -> np.ndarray:
        """The setting (P,) mm in ``names`` order (unset: 0); CalibrationError naming an unknown label."""
        unknown = sorted(set(self.setting) - set(names))
        if unknown:
            raise CalibrationError(f"calibration entry {self.name}: unknown parameter {unknown[0]!r} in its setting; "
                                   f"the bases have {list(names)}")
        return np.array([self.setting.get(label, 0.0) for label in names])


@dataclass(frozen=True)
class Reference:
    """A REF.json read for one set of bases, ready to make fields of their model reference-relative.

    path: the file as given; name: the entry's name; bases_id: the bases it was prepared with (:meth:`relative`
    refuses fields of other bases: a reference is read again for them); offset: what it takes off each field (two
    float64 per skin node: 16 bytes a node, 0.5 MB on the default hood, 3 MB at paper resolution); sources: the
    REF.json and the file it names as :func:`file_key` saw them before they were read."""

    path: str
    name: str
    bases_id: str
    offset: ReferenceOffset
    sources: tuple[tuple[str, int, int], ...]

    @property
    def model_id(self) -> str:
        return self.offset.model_id

    @property
    def resolved(self) -> str:
        """The REF.json's path resolved (absolute, through links): one name for one file, however it was given."""
        return self.sources[0][0]

    def label(self, scope: str) -> str:
        """What a result says of the reference it used: "<scope>:<resolved path>" ("cell:PATH" for a reference of
        every part, "part:PATH" for one part's own), so two spellings of one file compare equal."""
        return f"{scope}:{self.resolved}"

    def reads(self, source: tuple[str, int, int]) -> bool:
        """Whether reading the REF.json of :func:`file_key` ``source`` now would read what this reference read: the
        same file, unchanged, and the file it names unchanged since (modification time and size)."""
        try:
            return source == self.sources[0] and all(file_key(key[0]) == key for key in self.sources[1:])
        except OSError:
            return False

    def relative(self, field: DisplacementField, bases: Bases) -> DisplacementField:
        """``field`` as measured - reference + the model's field at the reference's setting (core.loop.calibration),
        for estimation with ``bases``: CalibrationError when the reference was prepared for other bases (its model's
        field at the setting, its scan reading are theirs), saying to read it again."""
        from hood_decomp.io.bases import loaded_bases_id

        used = loaded_bases_id(bases)
        if used != self.bases_id:
            raise CalibrationError(f"reference {self.path} was read for bases {self.bases_id}, the field is used with "
                                   f"bases {used}: read the reference again for them")
        return self.offset.relative(field)


def file_key(path: str | Path) -> tuple[str, int, int]:
    """(resolved path, modification time ns, size bytes) of ``path``: a file read again is read anew when any of them
    changed. OSError when it cannot be seen."""
    resolved = Path(path).resolve()
    stat = resolved.stat()
    return str(resolved), stat.st_mtime_ns, stat.st_size


def read_reference(path: str | Path, bases: Bases, min_coverage: float = 0.2) -> Reference:
    """The reference of REF.json ``path`` (one entry, :func:`read_entries`) prepared for ``bases``: its field read on
    their skin (a scan with ``min_coverage``), its setting checked against their parameters, the model's own field at
    that setting solved once. CalibrationError naming the problem: the file (unreadable, not one entry, a file outside
    its directory, an unknown parameter), a reference of another model_id, or bases without the reduced model the
    reference needs."""
    from hood_decomp.core.loop.calibration import reference_offset
    from hood_decomp.io.bases import loaded_bases_id

    if bases.reduced_model is None:
        raise CalibrationError(f"reference {path}: the bases of model {bases.model_id} hold no reduced model (build "
                               "them with --model), which a reference needs")
    try:  # taken before reading: a change while it is read shows later
        source = file_key(path)
    except OSError:
        source = (str(path), -1, -1)  # read_entries names the problem
    entry = read_entries(path, bases.skin, min_coverage, single=True)[0]
    setting = entry.setting_vector(bases.names)
    # a scanned reference's slide and bias need the bases' reading, prepared once (none for a field)
    reading = bases.reading() if entry.field.errors.kind == "scan" else None
    try:
        offset = reference_offset(bases.reduced_model, entry.field, setting, reading)
    except CalibrationError as error:
        raise CalibrationError(f"reference {path}: {error}") from error
    return Reference(str(path), entry.name, loaded_bases_id(bases), offset, (source, entry.source))


def read_entries(path: str | Path, skin: SkinSurface, min_coverage: float = 0.2, single: bool = False
                 ) -> list[FieldEntry]:
    """The entries of a CAL.json (``single``: a REF.json, exactly one entry) with their fields read on ``skin``.
    Raises CalibrationError naming the problem (and the entry); a field or scan that cannot be read names its file."""
    path = Path(path)
    what = "reference" if single else "calibration"
    try:
        data = loads_strict(read_small_file(path, MAX_BYTES, CalibrationError, f"{what} file").decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise CalibrationError(f"{what} file {path} cannot be read as JSON: {error}") from error
    if isinstance(data, dict):
        data = [data]
    if not isinstance(data, list) or not data or not all(isinstance(e, dict) for e in data):
        raise CalibrationError(f"{what} file {path}: expected a list of entries (objects with 'field' or 'scans' "
                               "and 'setting')")
    if single and len(data) != 1:
        raise CalibrationError(f"reference file {path}: expected one entry, got {len(data)}")
    if len(data) > MAX_ENTRIES:
        raise CalibrationError(f"{what} file {path}: {len(data)} entries, at most {MAX_ENTRIES}")
    base = path.resolve().parent
    return [_entry(raw, index, base, path, skin, min_coverage) for index, raw in enumerate(data)]


def _inside(base: Path, text: object, where: str) -> Path:
    """A file named in an entry: relative, inside the JSON file's directory, existing."""
    if not isinstance(text, str) or not text or "\x00" in text:
        raise CalibrationError(f"{where}: a file name must be a non-empty string")
    if Path(text).is_absolute():
        raise CalibrationError(f"{where}: {text!r} is absolute; name files relative to the calibration file")
    resolved = (base / text).resolve()
    if not resolved.is_relative_to(base):
        raise CalibrationError(f"{where}: {text!r} leaves the calibration file's directory")
    if not resolved.is_file():
        raise CalibrationError(f"{where}: {text!r} is not a file")
    return resolved


def _entry(raw: dict, index: int, base: Path, path: Path, skin: SkinSurface, min_coverage: float) -> FieldEntry:
    from hood_decomp.io.fields import read_field
    from hood_decomp.io.scans import field_from_scan_file

    where = f"{path.name} entry {index}"
    unknown = sorted(set(raw) - ENTRY_KEYS)
    if unknown:
        raise CalibrationError(f"{where}: unknown key {unknown[0]!r}; an entry has {sorted(ENTRY_KEYS)}")
    if ("field" in raw) == ("scans" in raw):
        raise CalibrationError(f"{where}: give exactly one of 'field' and 'scans'")
    setting = raw.get("setting")
    if not isinstance(setting, dict) or not all(
            isinstance(k, str) and isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            and abs(v) <= 1000.0 for k, v in setting.items()):
        raise CalibrationError(f"{where}: 'setting' must map parameter labels to finite numbers of mm (|x| <= 1000)")
    if "field" in raw:
        file, scan = _inside(base, raw["field"], where), False
    else:
        scans = raw["scans"]
        if not isinstance(scans, list) or not scans:
            raise CalibrationError(f"{where}: 'scans' must be a non-empty list of scan files")
        if len(scans) > 1 or raw.get("poses"):
            raise CalibrationError(f"{where}: several views with scanner poses need the multi-view fusion (issue 17),"
                                   " not in this build; give one scan (registered by its markers or stored pose)")
        file, scan = _inside(base, scans[0], where), True
    try:
        source = file_key(file)
    except OSError as error:
        raise CalibrationError(f"{where}: {file.name} cannot be read: {error.strerror}") from error
    name = raw.get("name")
    name = name if isinstance(name, str) and name else str(raw.get("field") or raw["scans"][0])
    try:
        field = field_from_scan_file(skin, file, min_coverage) if scan else read_field(file, skin)[0]
    except HoodDecompError as error:
        raise CalibrationError(f"{where} ({name}): {error}") from error
    return FieldEntry(name=name[:200], field=field, setting={k: float(v) for k, v in setting.items()},
                      source=source)
