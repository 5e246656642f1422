"""Scan files (.ply, :mod:`hood_decomp.io.ply`) to the displacement field of the skin they show: one scan, or several
views of one part each with its pose (its own POSE.json, else the pose stored in the PLY), fused into one field."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

from hood_decomp.core.scan.fusion import FusedField, ScanView, fuse_views
from hood_decomp.core.types import DisplacementField, SkinSurface
from hood_decomp.io.ply import read_scan
from hood_decomp.io.poses import read_pose_file

logger = logging.getLogger(__name__)

#: (scan file, its POSE.json or None)
ScanInput = tuple[str | os.PathLike, str | os.PathLike | None]


def scan_file_view(path: str | os.PathLike, pose_path: str | os.PathLike | None = None) -> ScanView:
    """One view from a scan file: its points and markers, and its pose from ``pose_path`` (source "file") or from the
    file's stored scanner pose (source "ply"), else none. Named by the file's path in errors."""
    scan = read_scan(path)
    if pose_path is not None:
        pose, source = read_pose_file(pose_path), "file"
    else:
        pose, source = scan.scanner_pose, "ply" if scan.scanner_pose is not None else "none"
    has_markers = scan.markers.shape[0] >= 3
    return ScanView(scan.points, pose, scan.markers if has_markers else None,
                    scan.markers_nominal if has_markers else None, name=str(path), pose_source=source)


def scan_file_views(scans: Sequence[ScanInput]) -> list[ScanView]:
    """The views of ``scans`` (:func:`scan_file_view` of each), in their order."""
    return [scan_file_view(path, pose) for path, pose in scans]


def fused_field_from_scan_files(skin: SkinSurface, scans: Sequence[ScanInput], min_coverage: float = 0.2,
                                views: Sequence[ScanView] | None = None,
                                marker_std_mm: float | None = None) -> FusedField:
    """The field of one part from its views' scan files (:func:`scan_file_view`), fused
    (:func:`hood_decomp.core.scan.fusion.fuse_views`): a lone scan without a pose is in the part frame (or registered
    by its markers); several views each need a pose, and one without is refused by its file name. ``min_coverage``
    applies to the fused field (and to a lone scan). ``views``: :func:`scan_file_views` of ``scans`` when the caller
    read them already (a one-off run reads them while the bases load). ``marker_std_mm``: the scanner's stated
    marker-centre noise (None: estimated per scan from its marker residual). Raises ScanError naming the file and its
    problem."""
    views = scan_file_views(scans) if views is None else views
    fused = fuse_views(skin, views, min_coverage=min_coverage,
                       min_view_coverage=min_coverage if len(views) == 1 else 0.02, marker_std_mm=marker_std_mm)
    for view in fused.views:
        logger.info("scan %s: %s pose, registered by %s, coverage %.1f%%, noise %.4f mm", Path(view.name).name,
                    view.pose_source, view.registration.method, 100 * view.field.coverage, view.field.noise_rms)
    return fused


def field_from_scan_file(skin: SkinSurface, path: str | Path, min_coverage: float = 0.2) -> DisplacementField:
    """The displacement field (N,) mm of ``skin`` that the scan file at ``path`` shows.

    Registration by the file's fixture markers (three or more), else by its stored scanner pose, else none (points
    already in the part frame); then the signed normal displacement per skin node
    (:func:`hood_decomp.core.scan.scan_field.field_from_scan`). Raises ScanError naming the file's problem (unreadable,
    empty, in metres, no overlap with the part, coverage below ``min_coverage``).
    """
    return fused_field_from_scan_files(skin, [(path, None)], min_coverage).field
