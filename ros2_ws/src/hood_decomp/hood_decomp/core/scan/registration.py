"""Registration of a scan to the nominal part that does not swallow the deformation being measured.

A best fit of the whole scan onto the nominal skin would remove every rigid-body-like part of the displacement field
(a hinge moved in X turns the hood about the fixed hinge almost rigidly). The paper avoids alignment altogether by
never moving part and scanner (section 4.3.1, markers on the fixture only check that nothing moved). Here:

1. Coarse: the fixture markers measured by the scanner are matched to their nominal positions (Kabsch, least
   squares); without markers, the cell's nominal scanner pose; without either, the identity (points already in the
   part frame).
2. Fine (optional): a point-to-surface Gauss-Newton alignment that uses only scan points on *datum* nodes, skin
   regions next to the fixed boundaries (the right hinge is fixed; the part is held at hinges and locks) where the
   displacement is zero by construction. It moves the part only along rigid-motion directions the datum determines
   well enough: the generalised eigenproblem of a motion metric against the datum's information matrix gives, per
   direction, the motion over the skin its noise would cause; directions above ``tolerance_mm`` stay at the coarse
   solution. The metric is |t|^2 + L^2 |omega|^2 for a twist about the datum centroid, L the RMS distance of the skin
   nodes from it: full 3D motion, not only its normal part (a crowned skin slides along itself under rotations about
   its centre of curvature, which barely change the normal field and are observed by nothing), and no cross terms,
   so that among motions that shift the datum equally the pure translation is preferred to a tilt about a far axis.
   A small patch near one hinge determines its normal shift, but its tilts (short lever, long extrapolation) and
   in-plane shifts (seen only through curvature) would spray noise over the far field, so they are left alone.

All lengths in mm, angles reported in degrees, transforms as (4, 4) homogeneous matrices mapping scanner-frame points
to the part frame: x_part = R x_scan + t.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hood_decomp.errors import ScanError


class NominalSurface(Protocol):
    """What the fine alignment needs from the prepared nominal skin (a fitted ScanFieldEstimator provides it)."""

    points_: np.ndarray
    frames_: np.ndarray  # (N, 3, 3) rows t1, t2, n
    max_distance_mm: float

    def point_distances(self, points_mm: np.ndarray): ...  # -> PointDistances (distance, node, tangent)

    def distance_gradient(self, located) -> np.ndarray: ...


@dataclass(frozen=True)
class RegistrationResult:
    """The scanner-to-part transform and how well it is determined.

    transform: (4, 4) x_part = R x_scan + t, mm.
    method: "markers", "pose" or "identity" for the coarse step, with "+datum" when the fine alignment ran.
    n_markers, marker_rms_mm: markers used and their RMS residual after the coarse fit (NaN without markers).
    n_datum_points, datum_rms_mm: scan points on datum nodes in the fine alignment and their RMS distance to the
        nominal skin after it (0 and NaN when no fine alignment ran).
    fine_translation_mm (3,), fine_rotation_deg (3,): the correction the fine alignment applied on top of the coarse
        transform (about the datum centroid).
    std_translation_mm (3,), std_rotation_deg (3,): standard deviations of a free datum fit (huge in directions the
        datum does not observe; NaN when no fine alignment ran).
    n_aligned: number of rigid-motion directions the fine alignment determined and corrected (0..6).
    alignment_std_mm: RMS over the skin of the displacement error the corrected directions may carry (noise).
    overlap: fraction of finite scan points (on a subsample) within ``max_distance_mm`` of the nominal skin.
    iterations, converged: of the fine alignment.
    pose_covariance: (6, 6) covariance of the coarse transform's error as a twist [omega rad (3), t mm (3)] about
        ``pose_center`` (3,) mm, part frame: sigma_m^2 (sum_k J_k^T J_k)^-1 over the markers (J_k = [-[q_k]x, I],
        q_k the nominal marker about its centroid), sigma_m the marker noise per coordinate (stated and not rejected
        by ``marker_noise``'s check, else from the marker residual with 3K - 6 degrees of freedom); zeros without
        markers (a nominal pose states none).
    marker_noise: the check of a stated marker noise against the marker residual (:func:`check_marker_noise`);
        None when no marker noise was stated or there were no markers.
    """

    transform: np.ndarray
    method: str
    n_markers: int
    marker_rms_mm: float
    n_datum_points: int
    datum_rms_mm: float
    fine_translation_mm: np.ndarray
    fine_rotation_deg: np.ndarray
    std_translation_mm: np.ndarray
    std_rotation_deg: np.ndarray
    overlap: float
    iterations: int
    converged: bool
    n_aligned: int
    alignment_std_mm: float
    pose_covariance: np.ndarray
    pose_center: np.ndarray
    marker_noise: MarkerNoiseCheck | None = None


#: default rate at which a correctly stated marker noise is rejected by :func:`check_marker_noise` (two-sided)
MARKER_CHECK_ALPHA = 0.001


@dataclass(frozen=True)
class MarkerNoiseCheck:
    """A stated marker-centre noise checked against the registration's own marker residual.

    With K markers of isotropic Gaussian centre noise sigma per coordinate, the residual sum of squares of the rigid
    fit over sigma^2 is chi-square with dof = 3K - 6 (18 for 8 markers). The stated value is rejected when that
    statistic is outside the two-sided (1 - alpha) interval: a scanner stating 2 times too little noise gives about
    4 times the expected statistic (p below 1e-9 for 8 markers), one stating too much too small a statistic.

    stated_mm: the stated noise; estimated_mm: the cloud's own estimate sqrt(RSS / dof); used_mm: what the pose
    covariance uses (stated, or the estimate when rejected); chi2, dof, p_value (two-sided), alpha; reason: "" when
    accepted, else one line naming the stated and the estimated noise and the test; clouds: how many clouds the
    statistic pools (1: this one; :class:`MarkerNoiseHistory`).
    """

    stated_mm: float
    estimated_mm: float
    used_mm: float
    chi2: float
    dof: int
    p_value: float
    alpha: float
    reason: str
    clouds: int = 1

    @property
    def accepted(self) -> bool:
        return not self.reason


def check_marker_noise(marker_rms_mm: float, n_markers: int, stated_mm: float, alpha: float = MARKER_CHECK_ALPHA,
                       earlier: tuple[float, int, int] = (0.0, 0, 0)) -> MarkerNoiseCheck:
    """Check ``stated_mm`` (marker-centre noise per coordinate, mm) against the RMS marker residual of a rigid fit
    to ``n_markers`` (>= 3) markers (RSS = K rms^2) at the two-sided rate ``alpha``; see :class:`MarkerNoiseCheck`.
    ``earlier``: (RSS mm^2, dof, clouds) of the same scanner's earlier clouds under the same statement
    (:class:`MarkerNoiseHistory`), pooled with this one; the estimate used on rejection stays this cloud's own.
    """
    from scipy.special import chdtrc  # chi-square survival function (scipy.stats.chi2.sf), imported when used

    if n_markers < 3:
        raise ScanError(f"a marker noise check needs at least 3 markers; got {n_markers}")
    if not (np.isfinite(stated_mm) and stated_mm > 0):
        raise ScanError(f"a stated marker noise must be a finite number > 0 mm, got {stated_mm}")
    own_rss, own_dof = n_markers * marker_rms_mm**2, 3 * n_markers - 6
    rss, dof, clouds = earlier[0] + own_rss, earlier[1] + own_dof, earlier[2] + 1
    chi2 = rss / stated_mm**2
    upper = float(chdtrc(dof, chi2))
    p_value = float(min(1.0, 2.0 * min(upper, 1.0 - upper)))
    estimated = float(np.sqrt(own_rss / own_dof))
    reason = ""
    if p_value < alpha:
        direction = "too small" if upper < 0.5 else "too large"
        residual = "the marker residual" if clouds == 1 else f"the marker residuals of the last {clouds} clouds"
        reason = (f"stated marker noise {stated_mm:.4g} mm is {direction} for {residual} (chi-square {chi2:.1f} "
                  f"with {dof} dof, p = {p_value:.1e} < {alpha:g}): the pose covariance uses the estimated "
                  f"{estimated:.4g} mm")
    return MarkerNoiseCheck(float(stated_mm), estimated, estimated if reason else float(stated_mm), float(chi2),
                            dof, p_value, float(alpha), reason, clouds)


#: how many of a scanner's recent clouds :class:`MarkerNoiseHistory` pools
MARKER_CHECK_CLOUDS = 20


class MarkerNoiseHistory:
    """One scanner's stated marker noise checked over its recent clouds (the scan node keeps one).

    A scanner's marker-centre noise is a constant of the scanner, so the residuals of its clouds under one statement
    pool: one cloud's 18 dof (8 markers) let 11 % of 2 x understatements through and with them the tails of the
    stated std (issue 15 run 9); 20 clouds' 360 dof reject a 1.5 x understatement almost surely. A new statement
    starts afresh. ``window``: clouds pooled (the latest included).
    """

    def __init__(self, window: int = MARKER_CHECK_CLOUDS, alpha: float = MARKER_CHECK_ALPHA) -> None:
        self.window = window
        self.alpha = alpha
        self._stated: float | None = None
        self._clouds: deque[tuple[float, int]] = deque(maxlen=max(window - 1, 0))
        self._lock = threading.Lock()

    def statement(self, stated_mm: float | None, markers_mm: np.ndarray | None,
                  markers_nominal_mm: np.ndarray | None) -> tuple[float | None, MarkerNoiseCheck | None]:
        """For one cloud with its markers (K, 3) measured and nominal (None: none): the marker noise to register it
        with (``marker_std_mm`` of :func:`register_scan`: the statement when the pooled check accepts it, whose own
        check then still applies; None, i.e. estimated, when it rejects it) and the pooled check (None without a
        statement or with fewer than 3 markers)."""
        if stated_mm is None or markers_mm is None or markers_nominal_mm is None or len(markers_mm) < 3:
            return stated_mm, None
        _, rms = rigid_from_markers(markers_mm, markers_nominal_mm)
        n_markers = len(markers_mm)
        with self._lock:
            if stated_mm != self._stated:
                self._clouds.clear()
                self._stated = stated_mm
            earlier = (sum(r for r, _ in self._clouds), sum(d for _, d in self._clouds), len(self._clouds))
            check = check_marker_noise(rms, n_markers, stated_mm, self.alpha, earlier)
            self._clouds.append((n_markers * rms**2, 3 * n_markers - 6))
        return (stated_mm if check.accepted else None), check


def marker_pose_covariance(nominal_mm: np.ndarray, marker_std_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (6, 6) of a least-squares rigid fit to markers (K, 3) mm with ``marker_std_mm`` noise per
    coordinate, as a twist [omega rad, t mm] about the markers' centroid; returns (covariance, centroid (3,))."""
    nominal = np.asarray(nominal_mm, dtype=np.float64)
    center = nominal.mean(axis=0)
    q = nominal - center
    information = np.zeros((6, 6))
    information[:3, :3] = np.sum(np.sum(q * q, axis=1)) * np.eye(3) - q.T @ q
    information[3:, 3:] = q.shape[0] * np.eye(3)
    return marker_std_mm**2 * np.linalg.inv(information), center


def _homogeneous(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = translation
    return transform


def rotation_from_vector(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector omega (3,), rad (Rodrigues)."""
    angle = float(np.linalg.norm(omega))
    if angle < 1e-15:
        return np.eye(3)
    k = omega / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def datum_mask_near(skin_points_mm: np.ndarray, centers_mm: np.ndarray, radius_mm: float) -> np.ndarray:
    """(N,) bool: skin nodes (N, 3) within ``radius_mm`` (3D) of any of the datum centres (K, 3), e.g. the patch
    centres of the model's fixed boundaries. Raises ScanError when no node is selected."""
    points = np.asarray(skin_points_mm, dtype=np.float64)
    centers = np.atleast_2d(np.asarray(centers_mm, dtype=np.float64))
    distance = np.min(np.linalg.norm(points[:, None, :] - centers[None, :, :], axis=2), axis=1)
    mask = distance <= radius_mm
    if not mask.any():
        raise ScanError(
            f"no skin node within {radius_mm} mm of the datum centres {centers.tolist()} "
            f"(nearest {distance.min():.1f} mm)"
        )
    return mask


def rigid_from_markers(measured_mm: np.ndarray, nominal_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares rigid transform (4, 4) taking measured markers (K, 3) onto nominal ones (K, 3) (Kabsch).

    Returns the transform and the RMS marker residual, mm. Raises ScanError for fewer than 3 markers, mismatched
    shapes or (nearly) collinear markers.
    """
    measured = np.asarray(measured_mm, dtype=np.float64)
    nominal = np.asarray(nominal_mm, dtype=np.float64)
    if measured.shape != nominal.shape or measured.ndim != 2 or measured.shape[1] != 3:
        raise ScanError(f"markers must be two matching (K, 3) arrays; got {measured.shape} and {nominal.shape}")
    if measured.shape[0] < 3:
        raise ScanError(f"registration needs at least 3 fixture markers; got {measured.shape[0]}")
    mc, nc = measured.mean(axis=0), nominal.mean(axis=0)
    spread = np.linalg.svd(nominal - nc, compute_uv=False)
    if spread[1] < 1e-3 * spread[0]:
        raise ScanError("fixture markers are collinear: the rotation about their line is undetermined")
    u, _, vt = np.linalg.svd((measured - mc).T @ (nominal - nc))
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    rotation = vt.T @ flip @ u.T
    translation = nc - rotation @ mc
    residual = measured @ rotation.T + translation - nominal
    return _homogeneous(rotation, translation), float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def register_scan(
    points_mm: np.ndarray,
    nominal: NominalSurface,
    *,
    scanner_pose: np.ndarray | None = None,
    markers_mm: np.ndarray | None = None,
    markers_nominal_mm: np.ndarray | None = None,
    datum_mask: np.ndarray | None = None,
    tolerance_mm: float = 0.005,
    max_marker_rms_mm: float = 0.5,
    max_iterations: int = 10,
    marker_std_mm: float | None = None,
    marker_check_alpha: float = MARKER_CHECK_ALPHA,
) -> RegistrationResult:
    """Register finite scan points (M, 3), mm, scanner frame, to the nominal skin; see the module docstring.

    tolerance_mm: the fine alignment corrects a rigid-motion direction only if the datum determines it to this RMS
        displacement over the skin.
    marker_std_mm: the scanner's marker-centre noise per coordinate (mm) for the pose covariance; None: estimated
        from the marker residual (3K - 6 degrees of freedom). A stated value is checked against that residual
        (:func:`check_marker_noise` at ``marker_check_alpha``); when rejected the estimate is used and
        ``marker_noise.reason`` says why, so a scanner stating too little noise cannot narrow the stated std.
    Raises ScanError when the markers do not fit each other (RMS above ``max_marker_rms_mm``: wrong matching or a
    moved marker) or a datum mask does not match the skin.
    """
    points = np.asarray(points_mm, dtype=np.float64)
    n_markers, marker_rms = 0, float("nan")
    pose_covariance, pose_center = np.zeros((6, 6)), np.zeros(3)
    marker_noise = None
    if markers_mm is not None and markers_nominal_mm is not None:
        coarse, marker_rms = rigid_from_markers(markers_mm, markers_nominal_mm)
        n_markers = int(np.asarray(markers_mm).shape[0])
        if marker_rms > max_marker_rms_mm:
            raise ScanError(
                f"fixture markers do not fit: RMS residual {marker_rms:.3f} mm after the best rigid fit "
                f"(expected below {max_marker_rms_mm} mm); a marker is mismatched or has moved"
            )
        method = "markers"
        # K markers (K >= 3) leave 3K - 6 >= 3 degrees of freedom for their noise; marker_rms^2 is sum / K
        sigma_m = marker_rms * np.sqrt(n_markers / (3 * n_markers - 6))
        if marker_std_mm is not None:
            marker_noise = check_marker_noise(marker_rms, n_markers, float(marker_std_mm), marker_check_alpha)
            sigma_m = marker_noise.used_mm
        pose_covariance, pose_center = marker_pose_covariance(markers_nominal_mm, sigma_m)
    elif scanner_pose is not None:
        coarse = np.asarray(scanner_pose, dtype=np.float64)
        if coarse.shape != (4, 4):
            raise ScanError(f"scanner_pose must be a (4, 4) transform; got {coarse.shape}")
        method = "pose"
    else:
        coarse, method = np.eye(4), "identity"

    nan3 = np.full(3, np.nan)
    fine = _FineResult(np.eye(4), 0, float("nan"), np.zeros(3), np.zeros(3), nan3, nan3, 0, True, 0, 0.0)
    if datum_mask is not None:
        datum = np.asarray(datum_mask, dtype=bool)
        if datum.shape != (nominal.points_.shape[0],):
            raise ScanError(
                f"datum_mask must have one entry per skin node ({nominal.points_.shape[0]}); got {datum.shape}"
            )
        if datum.any():
            moved = np.einsum("md,ed->me", points, coarse[:3, :3]) + coarse[:3, 3]
            fine = _fine_alignment(moved, nominal, datum, tolerance_mm, max_iterations)
            method += "+datum"
    transform = fine.transform @ coarse

    # Overlap on an even subsample (a raster scan's points come in order), so it costs nothing next to the field.
    sample = np.einsum("md,ed->me", points[:: max(1, points.shape[0] // 20000)], transform[:3, :3]) + transform[:3, 3]
    overlap = float(np.mean(nominal.point_distances(sample).node >= 0)) if sample.shape[0] else 0.0
    return RegistrationResult(
        transform=transform,
        method=method,
        n_markers=n_markers,
        marker_rms_mm=marker_rms,
        n_datum_points=fine.n_points,
        datum_rms_mm=fine.rms,
        fine_translation_mm=fine.translation,
        fine_rotation_deg=np.degrees(fine.rotation),
        std_translation_mm=fine.std_translation,
        std_rotation_deg=np.degrees(fine.std_rotation),
        overlap=overlap,
        iterations=fine.iterations,
        converged=fine.converged,
        n_aligned=fine.n_aligned,
        alignment_std_mm=fine.field_std,
        pose_covariance=pose_covariance,
        pose_center=pose_center,
        marker_noise=marker_noise,
    )


@dataclass(frozen=True)
class _FineResult:
    transform: np.ndarray
    n_points: int
    rms: float
    translation: np.ndarray
    rotation: np.ndarray
    std_translation: np.ndarray
    std_rotation: np.ndarray
    iterations: int
    converged: bool
    n_aligned: int
    field_std: float


def _fine_alignment(
    points: np.ndarray, nominal: NominalSurface, datum: np.ndarray, tolerance: float, max_iterations: int
) -> _FineResult:
    """Gauss-Newton on the datum points, min sum d(R (p - c) + c + t)^2, restricted to the well-determined subspace.

    The twist xi = (omega rad, t mm) about the datum centroid c; motion metric F = diag(L^2, L^2, L^2, 1, 1, 1). With
    the datum information H = J^T J / s^2 (s the robust residual scale), eigh(F, H) gives directions v (v^T H v = 1)
    whose posterior motion variance is the eigenvalue; only directions with variance below tolerance^2 are updated.
    """
    # Candidates: points near the datum nodes' bounding box (cheap), then exact datum membership per iteration.
    datum_points = nominal.points_[datum]
    margin = nominal.max_distance_mm + 5.0
    lo, hi = datum_points.min(axis=0) - margin, datum_points.max(axis=0) + margin
    candidates = points[np.all((points >= lo) & (points <= hi), axis=1)]
    center = datum_points.mean(axis=0)
    lever2 = float(np.mean(np.sum((nominal.points_ - center) ** 2, axis=1)))
    motion_metric = np.diag([lever2, lever2, lever2, 1.0, 1.0, 1.0])
    xi = np.zeros(6)
    nan3 = np.full(3, np.nan)
    information = np.zeros((6, 6))
    keep = np.zeros(6, bool)
    variance = np.full(6, np.inf)
    rms, n_used, converged, iteration = float("nan"), 0, False, 0
    for iteration in range(1, max_iterations + 1):
        rotation = rotation_from_vector(xi[:3])
        current = np.einsum("md,ed->me", candidates - center, rotation) + center + xi[3:]
        located = nominal.point_distances(current)
        use = located.node >= 0
        use[use] = datum[located.node[use]]
        d = located.distance[use]
        if d.size < 6:
            return _FineResult(np.eye(4), int(d.size), float("nan"), np.zeros(3), np.zeros(3), nan3, nan3,
                               iteration, False, 0, 0.0)  # fmt: skip
        # Robust: gross outliers near the datum (clamps, mixed pixels) must not steer the part.
        med = float(np.median(d))
        sigma = max(1.4826 * float(np.median(np.abs(d - med))), 1e-3)
        inlier = np.abs(d - med) <= 4.0 * sigma
        d = d[inlier]
        kept = type(located)(located.distance[use][inlier], located.node[use][inlier], located.tangent[use][inlier])
        gradient = nominal.distance_gradient(kept)
        jacobian = np.column_stack([np.cross(current[use][inlier] - center, gradient), gradient])
        information = jacobian.T @ jacobian / sigma**2
        regularised = information + 1e-12 * np.trace(information) * np.eye(6)
        from scipy.linalg import eigh  # the datum fine alignment only

        variance, directions = eigh(motion_metric, regularised)
        keep = variance <= tolerance**2
        basis = directions[:, keep]
        step = -basis @ (basis.T @ (jacobian.T @ d / sigma**2))
        xi = xi + step
        rms, n_used = float(np.sqrt(np.mean(d**2))), int(d.size)
        if np.linalg.norm(step[3:]) < 1e-5 and np.linalg.norm(step[:3]) < 1e-8:
            converged = True
            break
    rotation = rotation_from_vector(xi[:3])
    transform = _homogeneous(rotation, center + xi[3:] - rotation @ center)
    with np.errstate(divide="ignore", invalid="ignore"):
        std = np.sqrt(np.diag(np.linalg.pinv(information)))
    field_std = float(np.sqrt(np.sum(variance[keep])))
    return _FineResult(transform, n_used, rms, xi[3:].copy(), xi[:3].copy(), std[3:], std[:3], iteration, converged,
                       int(keep.sum()), field_std)  # fmt: skip
