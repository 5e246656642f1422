"""Opening the project's HDF5 files (ensemble stores, bases) with errors that name the file and what it should be."""

from __future__ import annotations

from pathlib import Path

import h5py

from hood_decomp.errors import HoodDecompError


def open_hdf5(path: str | Path, what: str, error: type[HoodDecompError]) -> h5py.File:
    """Open an existing HDF5 file for reading; raise ``error`` naming ``what`` (e.g. "bases file") when the file is
    missing or not HDF5. Schema checks stay with each reader."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{what} {path} does not exist")
    try:
        return h5py.File(path, "r")
    except OSError as failure:
        raise error(f"{path} is not an HDF5 {what}: {failure}") from failure
