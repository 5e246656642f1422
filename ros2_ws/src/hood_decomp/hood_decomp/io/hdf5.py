"""Opening the project's HDF5 files (ensemble stores, bases): the one place that decides what an HDF5 file may hold.

A file from elsewhere must not make the program read another file, run code or exhaust memory. h5py follows external
links (another .h5 file), external storage (a dataset whose bytes live in any other file, e.g. /etc/passwd) and
virtual datasets (bytes from other files) silently, and an unknown compression filter makes HDF5 search its plugin
path for a shared library to load. So :func:`open_hdf5` walks the whole file before anything is read and refuses:

- any link that is not a hard link (external links, soft links, dangling or not: the project's files hold only hard
  links, so a soft link is never needed and a dangling one is an error anyway),
- datasets with external storage or virtual (mapped) storage,
- datasets with a filter other than gzip, shuffle and fletcher32 (what h5py writes; no plugin is ever loaded),
- dtypes other than numbers, booleans and strings (no object references, no compound or variable-length numbers),
- datasets whose shape claims more memory than the file could hold (:data:`MAX_EXPANSION` times the file size,
  plus :data:`SLACK_BYTES`): a 1 kB file cannot make the reader allocate hundreds of GiB.

:class:`Reader` then reads datasets and attributes with the expected kind, shape (named dimensions bound on first
use, so a wrong component count is named as such) and finite values, each problem a one-line error naming the file,
the object, what was expected and what was found.
"""

from __future__ import annotations

import math
import mmap
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np

from hood_decomp.errors import HoodDecompError
from hood_decomp.io.small_files import descriptor_path, open_regular

#: gzip (1), shuffle (2) and fletcher32 (3): the filters h5py applies itself; any other id would load a plugin
ALLOWED_FILTERS = {1: "gzip", 2: "shuffle", 3: "fletcher32"}
#: a dataset may claim at most this many times the file's size in memory: gzip level 1 with shuffle compresses the
#: project's float arrays 1-4 times, constant blocks more, which SLACK_BYTES absorbs
MAX_EXPANSION = 64
SLACK_BYTES = 256 * 2**20
_NUMBER_KINDS = {"f": "float", "i": "integer", "u": "integer", "b": "bool"}


#: what h5py raises for a damaged file (corrupt metadata surfaces as any of these, at any access)
_DAMAGE = (OSError, RuntimeError, KeyError, ValueError, TypeError, IndexError, OverflowError)


@contextmanager
def open_hdf5(path: str | Path, what: str, error: type[HoodDecompError]) -> Iterator[h5py.File]:
    """Open an existing HDF5 file for reading after :func:`audit_hdf5`, for a ``with`` block; raise ``error`` naming
    ``what`` (e.g. "bases file") when the file is missing, not HDF5, or holds anything the module docstring refuses,
    and turn what h5py raises for damaged metadata anywhere in the block into ``error`` too. Schema checks stay with
    each reader (:class:`Reader`)."""
    path = Path(path)
    if not path.exists():  # anything else that is not a regular file is named by open_regular
        raise error(f"{what} {path} does not exist")
    try:  # HDF5 takes a name: it gets the descriptor's, so it reads the file checked here (never a FIFO)
        handle = open_regular(path, error, what)
    except OSError as failure:
        raise error(f"cannot open {what} {path}: {failure.strerror}") from failure
    with handle:
        try:
            h5 = h5py.File(descriptor_path(handle, path), "r", locking=False)
        except _DAMAGE as failure:
            raise error(f"{path} is not an HDF5 {what}: {_first_line(failure)}") from failure
        try:
            audit_hdf5(h5, path, error)
            yield h5
        except _DAMAGE as failure:
            raise error(f"{path}: damaged {what}: {type(failure).__name__}: {_first_line(failure)[:200]}") from failure
        finally:
            h5.close()


def _first_line(failure: BaseException) -> str:
    return str(failure).splitlines()[0] if str(failure) else type(failure).__name__


def audit_hdf5(h5: h5py.File, path: Path, error: type[HoodDecompError]) -> None:
    """Walk every link of ``h5`` without following anything but hard links; raise ``error`` at the first object the
    module docstring refuses."""
    limit = MAX_EXPANSION * os.path.getsize(path) + SLACK_BYTES
    seen: set[int] = set()
    pending: list[h5py.Group] = [h5]
    while pending:
        group = pending.pop()
        address = h5py.h5o.get_info(group.id).addr
        if address in seen:
            continue
        seen.add(address)
        for name in list(group.keys()):
            where = f"{group.name.rstrip('/')}/{name}"
            try:
                link = group.get(name, getlink=True)
            except _DAMAGE as failure:
                raise error(f"{path}: link {where} cannot be read: {_first_line(failure)}") from failure
            if isinstance(link, h5py.ExternalLink):
                raise error(f"{path}: {where} is an external link to {link.filename}:{link.path}; refused (a "
                            "hood_decomp file holds only its own data)")
            if not isinstance(link, h5py.HardLink):
                raise error(f"{path}: {where} is a {type(link).__name__}; refused (a hood_decomp file holds only "
                            "hard links)")
            try:
                item = group[name]
            except _DAMAGE as failure:
                raise error(f"{path}: object {where} cannot be opened: {_first_line(failure)}") from failure
            if isinstance(item, h5py.Group):
                pending.append(item)
            elif isinstance(item, h5py.Dataset):
                _audit_dataset(item, path, limit, error)


def _audit_dataset(dataset: h5py.Dataset, path: Path, limit: int, error: type[HoodDecompError]) -> None:
    where = f"{path}: dataset {dataset.name}"
    plist = dataset.id.get_create_plist()
    if plist.get_external_count():
        target = plist.get_external(0)[0].decode(errors="replace")
        raise error(f"{where} keeps its data in the external file {target!r}; refused (external storage)")
    if dataset.is_virtual:
        raise error(f"{where} is a virtual dataset (data mapped from other files); refused")
    for index in range(plist.get_nfilters()):
        code = plist.get_filter(index)[0]
        if code not in ALLOWED_FILTERS:
            raise error(f"{where} uses HDF5 filter {code}; only {sorted(ALLOWED_FILTERS.values())} are read")
    kind = _dtype_kind(dataset.dtype)
    if kind is None:
        raise error(f"{where} has dtype {dataset.dtype} ({_describe_dtype(dataset.dtype)}); expected numbers or "
                    "strings")
    if dataset.shape is None:
        return
    claimed = math.prod(dataset.shape) * (dataset.dtype.itemsize if kind != "str" else 16)
    if claimed > limit:
        raise error(f"{where} claims shape {dataset.shape} ({claimed / 2**30:.3g} GiB), far more than the "
                    f"{os.path.getsize(path)}-byte file can hold")


def _dtype_kind(dtype: np.dtype) -> str | None:
    """"float", "integer", "bool" or "str" for the dtypes a hood_decomp file may hold, else None."""
    if h5py.check_string_dtype(dtype) is not None:
        return "str"
    return _NUMBER_KINDS.get(dtype.kind) if dtype.fields is None and dtype.subdtype is None else None


def _describe_dtype(dtype: np.dtype) -> str:
    if h5py.check_ref_dtype(dtype) is not None:
        return "object references"
    if h5py.check_vlen_dtype(dtype) is not None:
        return "variable-length numbers"
    if dtype.fields is not None:
        return "compound"
    return "not numbers or strings"


class Reader:
    """Typed, shape-checked reads from an audited file. ``dims`` binds dimension names (e.g. "N", "K") to sizes on
    first use; every later use must agree, so a wrong shape names the dimension and where it was fixed."""

    def __init__(self, h5: h5py.File, path: str | Path, error: type[HoodDecompError], mapped: bool = False) -> None:
        """``mapped``: datasets stored plainly (contiguous, no filter, native numbers) are read-only views of the file
        mapped into memory (:meth:`_mapped_view`), not copies: a fresh process's page cache pages are used as they
        are, where a copy costs fresh memory (about 1 ms per MB on this project's machines, most of a one-off
        `estimate --scan`'s file reading). For a process that ends soon after (the command line): a file truncated
        while it is mapped ends the process (SIGBUS); replacing it (a rename, as the writers do) does not."""
        self.h5, self.path, self.error, self.mapped = h5, Path(path), error, mapped
        self.dims: dict[str, tuple[int, str]] = {}
        self._file_map: mmap.mmap | None = None

    def _object(self, name: str) -> h5py.HLObject:
        if name not in self.h5:
            raise self.error(f"{self.path}: {name} is missing")
        return self.h5[name]

    def bind(self, dim: str, size: int, source: str) -> None:
        """Bind ``dim`` to ``size`` (taken from ``source``) or check it against its earlier binding."""
        if dim not in self.dims:
            self.dims[dim] = (size, source)
        elif self.dims[dim][0] != size:
            bound, origin = self.dims[dim]
            raise self.error(f"{self.path}: {source} has {dim} = {size}, but {origin} has {dim} = {bound}")

    def array(self, name: str, dims: Sequence[str], kind: str = "float", rows: slice | None = None) -> np.ndarray:
        """Dataset ``name`` as an array of ``kind`` ("float", "integer" or "bool") with named dimensions ``dims``
        (a digit string is a fixed size); floats must be finite. ``rows`` reads a slice of the first dimension."""
        dataset = self._object(name)
        if not isinstance(dataset, h5py.Dataset):
            raise self.error(f"{self.path}: {name} is a group, expected a dataset")
        found = _dtype_kind(dataset.dtype)
        allowed = {"float": {"float", "integer"}, "integer": {"integer"}, "bool": {"bool", "integer"}}[kind]
        if found not in allowed:
            raise self.error(f"{self.path}: {name} holds {found or dataset.dtype}, expected {kind}")
        shape = dataset.shape or ()
        if len(shape) != len(dims):
            raise self.error(f"{self.path}: {name} has shape {shape}, expected ({', '.join(dims)})")
        for dim, size in zip(dims, shape, strict=True):
            if dim.isdigit():
                if int(dim) != size:
                    raise self.error(f"{self.path}: {name} has shape {shape}, expected ({', '.join(dims)})")
            else:
                self.bind(dim, size, name)
        mapped = self._mapped_view(dataset) if rows is None else None
        values = dataset[()] if mapped is None else mapped
        if kind == "float" and values.size and not np.all(np.isfinite(values)):
            bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
            raise self.error(f"{self.path}: {name} holds {bad} non-finite values (NaN or inf)")
        return values

    def _mapped_view(self, dataset: h5py.Dataset) -> np.ndarray | None:
        """The dataset as a read-only array over the mapped file when :attr:`mapped` and it is stored plainly (its
        bytes in one piece at a known offset inside the file), else None (read it through h5py). What the view holds
        is checked like any read: finiteness here, ``bases_id``/``prepared_id`` by the caller."""
        if not self.mapped or dataset.chunks is not None or not dataset.dtype.isnative or not dataset.shape:
            return None
        offset = dataset.id.get_offset()
        size = dataset.size * dataset.dtype.itemsize
        if offset is None or dataset.id.get_create_plist().get_nfilters() or self.h5.userblock_size:
            return None
        if self._file_map is None:
            # the mapping outlives the descriptor; a FIFO swapped in since open_hdf5 is refused, not waited on, and
            # another file's bytes fail the caller's bases_id check
            with open_regular(self.path, self.error, "file") as file:
                length = os.fstat(file.fileno()).st_size
                if not length:
                    return None
                self._file_map = mmap.mmap(file.fileno(), length, access=mmap.ACCESS_READ)
        if offset + size > len(self._file_map):
            raise self.error(f"{self.path}: {dataset.name} claims bytes {offset}..{offset + size} of a "
                             f"{len(self._file_map)}-byte file")
        return np.frombuffer(self._file_map, dataset.dtype, dataset.size, offset).reshape(dataset.shape)

    def strings(self, name: str, dim: str) -> tuple[str, ...]:
        """A one-dimensional string dataset (HDF5 variable-length UTF-8) of length ``dim``."""
        dataset = self._object(name)
        if not isinstance(dataset, h5py.Dataset) or _dtype_kind(dataset.dtype) != "str" or dataset.ndim != 1:
            raise self.error(f"{self.path}: {name} must be a one-dimensional string array, found "
                             f"{getattr(dataset, 'dtype', 'a group')} {getattr(dataset, 'shape', '')}")
        self.bind(dim, dataset.shape[0], name)
        try:
            return tuple(s.decode() if isinstance(s, bytes) else str(s) for s in dataset[()])
        except UnicodeDecodeError as failure:
            raise self.error(f"{self.path}: {name} holds text that is not UTF-8") from failure

    def attr(self, name: str, key: str, kind: str) -> str | int | float | bool:
        """Attribute ``key`` of object ``name`` ("/" for the root) as ``kind`` ("str", "int", "float" (finite),
        "float_or_nan" or "bool")."""
        attrs = self._object(name).attrs if name != "/" else self.h5.attrs
        where = f"{self.path}: attribute {key!r} of {name}"
        if key not in attrs:
            raise self.error(f"{where} is missing")
        try:
            value = attrs[key]
        except _DAMAGE as failure:
            raise self.error(f"{where} cannot be read: {_first_line(failure)}") from failure
        if isinstance(value, np.ndarray) and value.size == 1 and value.dtype.kind != "O":
            value = value.reshape(()).item()
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, bytes):
            try:
                value = value.decode()
            except UnicodeDecodeError:
                raise self.error(f"{where} is not UTF-8 text") from None
        if kind == "str" and isinstance(value, str):
            return value
        if kind == "bool" and isinstance(value, bool | int) and value in (0, 1):
            return bool(value)
        if kind == "int" and isinstance(value, int) and not isinstance(value, bool):
            return value
        if kind in ("float", "float_or_nan") and isinstance(value, int | float) and not isinstance(value, bool):
            if kind == "float" and not math.isfinite(value):
                raise self.error(f"{where} is {value}, expected a finite number")
            if math.isinf(value):
                raise self.error(f"{where} is {value}, expected a number or NaN")
            return float(value)
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        raise self.error(f"{where} is {shown} ({type(value).__name__}), expected {kind.replace('_or_nan', '')}")
