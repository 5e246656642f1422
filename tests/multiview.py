"""What the multi-view tests share: one part of the coarse hood scanned in partial views by the synthetic scanner."""

from __future__ import annotations

import numpy as np

from hood_decomp.synthetic.scanner import ScannerConfig, SyntheticScan, synthesize_scan

#: three partial views from tilted robot poses: aim (fractions of the skin's half extents) and tilt (deg)
VIEWS = (((-0.55, -0.45), (12.0, -12.0)), ((0.55, -0.45), (12.0, 12.0)), ((0.0, 0.5), (-12.0, 0.0)))


def scanned_part(case, truth: dict[str, float], seed: int, **config: object) -> tuple[object, list[SyntheticScan]]:
    """The FE member of ``truth`` (label -> mm, others 0) on ``case`` (a tests.conftest HoodCase) and one 60k-point
    scan per view of :data:`VIEWS` (``config`` adds to or overrides the scanner set-up; seeds seed, seed + 1, ...)."""
    from hood_decomp.core.fe.ensemble import solve_members

    names = list(case.reduced.names)
    state = np.zeros(len(names))
    for label, value in truth.items():
        state[names.index(label)] = value
    member = solve_members(case.reduced, state[None])
    scans = []
    for k, (aim, tilt) in enumerate(VIEWS):
        setup = {"n_points": 60_000, "noise_mm": 0.02, "view_center": aim, "view_tilt_deg": tilt, "fov_deg": 40.0,
                 "standoff_mm": 1500.0, **config}
        scans.append(synthesize_scan(case.skin, member.displacement[0], ScannerConfig(**setup), seed=seed + k))
    return member, scans
