"""Scanner pose files (POSE.json): a rigid 4 x 4 transform, row-major, mm, part <- scanner (x_part = T x_scan).

Accepted: a JSON list of 4 rows of 4 numbers, a flat list of 16 numbers, or an object whose ``"pose"`` (or
``"scanner_pose"``) holds either. Checked by :func:`hood_decomp.core.scan.fusion.check_pose` (finite, orthonormal
rotation within its tolerance, no mirror, last row [0, 0, 0, 1]); anything else is a ScanError naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from hood_decomp.core.scan.fusion import check_pose
from hood_decomp.errors import ScanError
from hood_decomp.io.json_values import loads_strict
from hood_decomp.io.small_files import read_small_file

#: a pose file is 16 numbers; anything far larger is not one (and is not read whole)
MAX_POSE_FILE_BYTES = 64 * 1024


def read_pose_file(path: str | os.PathLike) -> np.ndarray:
    """The (4, 4) transform (mm, part <- scanner) in the JSON file at ``path``; ScanError naming the file otherwise."""
    path = Path(path)
    what = f"scanner pose {path}"
    try:
        if not path.exists():
            raise ScanError(f"{what}: no such file")
        # a pose file holds 16 numbers: MAX_POSE_FILE_BYTES is far more
        document = loads_strict(read_small_file(path, MAX_POSE_FILE_BYTES, ScanError, "scanner pose").decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise ScanError(f"{what}: not a readable JSON file: {' '.join(str(error).split())[:120]}") from None
    if isinstance(document, dict):
        key = next((k for k in ("pose", "scanner_pose") if k in document), None)
        if key is None:
            raise ScanError(f"{what}: a JSON object needs a 'pose' entry (4 x 4, row-major, mm)")
        document = document[key]
    rows = document if isinstance(document, list) else None
    flat = rows if rows is not None and all(not isinstance(v, list) for v in rows) else None
    numbers = flat if flat is not None else [v for row in rows or [] for v in (row if isinstance(row, list) else [row])]
    if rows is None or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in numbers) or (
            flat is None and any(not isinstance(row, list) or len(row) != 4 for row in rows)):
        raise ScanError(f"{what}: expected 4 rows of 4 numbers (or 16 numbers), row-major, mm")
    return check_pose(np.array(numbers, dtype=np.float64), what)
