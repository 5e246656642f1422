"""Tolerance zones: acceptance criteria on regions of the skin, judged on a displacement field.

A zone is a set of skin nodes (those inside an axis-aligned box and/or a sphere in part coordinates, mm) with limits
on the signed normal displacement. The verdict of a field is OK when enough of the zone is seen and every seen node
lies within the limits; it names the worst node (farthest outside, or nearest to a limit when all are inside).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hood_decomp.core.types import DisplacementField, ToleranceZone, ZoneVerdict
from hood_decomp.errors import FieldError


def zone_nodes(points: np.ndarray, box: tuple[Sequence[float], Sequence[float]] | None = None,
               sphere: tuple[Sequence[float], float] | None = None) -> np.ndarray:
    """Indices (M,) int64 of the skin nodes ``points`` (N, 3) mm that lie inside every given shape: ``box`` (min
    corner, max corner), mm, bounds included; ``sphere`` (centre, radius), mm, surface included. At least one shape."""
    if box is None and sphere is None:
        raise ValueError("a zone needs a box or a sphere")
    inside = np.ones(len(points), dtype=bool)
    if box is not None:
        low, high = np.asarray(box[0], dtype=float), np.asarray(box[1], dtype=float)
        inside &= np.all((points >= low) & (points <= high), axis=1)
    if sphere is not None:
        centre, radius = np.asarray(sphere[0], dtype=float), float(sphere[1])
        inside &= np.sum((points - centre) ** 2, axis=1) <= radius**2
    return np.flatnonzero(inside).astype(np.int64)


def zone_verdicts(field: DisplacementField, zones: Sequence[ToleranceZone]) -> tuple[ZoneVerdict, ...]:
    """One :class:`ZoneVerdict` per zone for ``field`` (its normal displacement, (N,) mm, NaN where unseen).

    Per seen node of a zone the excess ``max(lower - w, w - upper)`` (mm, > 0 outside); the worst node has the
    largest excess. Raises FieldError when a zone names a node beyond the field's N (zones of another skin)."""
    values = np.asarray(field.normal_displacement, dtype=float)
    verdicts = []
    for zone in zones:
        if zone.nodes.size and int(zone.nodes.max()) >= values.size:
            raise FieldError(f"tolerance zone {zone.name!r} names skin node {int(zone.nodes.max())}, the field has "
                             f"{values.size} nodes (zones of another skin)")
        w = values[zone.nodes]
        seen = np.isfinite(w)
        coverage = float(seen.mean()) if w.size else 0.0
        if not seen.any():
            verdicts.append(ZoneVerdict(zone.name, False, zone.lower_mm, zone.upper_mm, float("nan"), -1, coverage, 0,
                                        "no node of the zone seen"))
            continue
        excess = np.maximum(zone.lower_mm - w[seen], w[seen] - zone.upper_mm)
        worst = int(np.argmax(excess))
        outside = int(np.count_nonzero(excess > 0.0))
        worst_value, worst_node = float(w[seen][worst]), int(zone.nodes[seen][worst])
        reasons = []
        if outside:
            reasons.append(f"{outside} seen node(s) outside [{zone.lower_mm:g}, {zone.upper_mm:g}] mm, worst "
                           f"{worst_value:+.3f} mm at node {worst_node}")
        if coverage < zone.min_coverage:
            reasons.append(f"{100 * coverage:.0f} % of the zone seen, {100 * zone.min_coverage:.0f} % needed")
        verdicts.append(ZoneVerdict(zone.name, not reasons, zone.lower_mm, zone.upper_mm, worst_value, worst_node,
                                    coverage, outside, "; ".join(reasons)))
    return tuple(verdicts)
