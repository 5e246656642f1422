"""A scan file (.ply, :mod:`hood_decomp.io.ply`) to the displacement field of the skin it shows."""

from __future__ import annotations

import logging
from pathlib import Path

from hood_decomp.core.scan.scan_field import field_from_scan
from hood_decomp.core.types import DisplacementField, SkinSurface
from hood_decomp.io.ply import read_scan

logger = logging.getLogger(__name__)


def field_from_scan_file(skin: SkinSurface, path: str | Path, min_coverage: float = 0.2) -> DisplacementField:
    """The displacement field (N,) mm of ``skin`` that the scan file at ``path`` shows.

    Registration by the file's fixture markers (three or more), else by its stored scanner pose, else none (points
    already in the part frame); then the signed normal displacement per skin node
    (:func:`hood_decomp.core.scan.scan_field.field_from_scan`). Raises ScanError naming the file's problem (unreadable,
    empty, in metres, no overlap with the part, coverage below ``min_coverage``).
    """
    scan = read_scan(path)
    has_markers = scan.markers.shape[0] >= 3
    field, registration = field_from_scan(
        skin,
        scan.points,
        scanner_pose=scan.scanner_pose,
        markers_mm=scan.markers if has_markers else None,
        markers_nominal_mm=scan.markers_nominal if has_markers else None,
        min_coverage=min_coverage,
    )
    logger.info("scan %s: registered by %s, coverage %.1f%%, noise %.4f mm", Path(path).name, registration.method,
                100 * field.coverage, field.noise_rms)
    return field
