"""From a scan to a displacement field: rigid registration (markers, datum surface) and one signed normal distance
per visible skin node with local smoothing and a validity mask; several views of one part fused into one field.

May import: ``hood_decomp.core.types`` and ``hood_decomp.errors`` only (never ``fe``, ``method`` or ``loop``).
"""

from hood_decomp.core.scan.fusion import (
    FusedField,
    ScanView,
    ViewResult,
    check_pose,
    fuse_fields,
    fuse_views,
    pose_difference,
    view_field,
)
from hood_decomp.core.scan.registration import RegistrationResult, register_scan, rigid_from_markers
from hood_decomp.core.scan.scan_field import (
    ScanFieldEstimator,
    field_from_scan,
    prepared_estimator,
    register_prepared_skin,
    smoothing_bias_correlation,
    warm_up,
)

__all__ = [
    "FusedField", "RegistrationResult", "ScanFieldEstimator", "ScanView", "ViewResult", "check_pose",
    "field_from_scan", "fuse_fields", "fuse_views", "pose_difference", "prepared_estimator",
    "register_prepared_skin", "register_scan", "rigid_from_markers", "smoothing_bias_correlation", "view_field",
    "warm_up",
]
