"""Write the scenario bags of bags/ (rosbag2 MCAP via rosbags) with their truth sidecars; rebuild them with

    scripts/with-env python scripts/make_bags.py [--out bags] [--points 40000]

Scenarios on the built-in hood at default resolution (the coarse grid's 30 mm node spacing is too coarse for a
scan-derived field to stay within the scan noise; the tests rebuild the same model and check its model_id against
the sidecar):
- clean: three scans at known boundary states, 0.005 mm noise, no occlusion.
- noisy_occluded: three scans with 0.05 mm noise, dropout holes, outliers and a lifted buffer.
- undeclared: two scans whose part has an effect the model does not declare (the fixed right hinge moved in Z).
- malformed: every kind of broken cloud of hood_decomp.ros.scan_bag.MALFORMED between two good scans.
"""

from __future__ import annotations

import argparse
import pathlib
import shutil
import sys

from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.ros.scan_bag import MALFORMED, write_scenario_bag
from hood_decomp.synthetic.scanner import ScannerConfig
from hood_decomp.synthetic.scenarios import make_scenario_scan

RESOLUTION = "default"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path(__file__).parents[1] / "bags")
    parser.add_argument("--points", type=int, default=80_000, help="scan points per cloud (keeps bags/ small)")
    args = parser.parse_args()
    model = build_hood(RESOLUTION)
    skin = skin_surface(model)
    solver = build_solver(model)
    reduced = reduce_model(solver)
    clean = ScannerConfig(n_points=args.points, noise_mm=0.005, outlier_fraction=0.0, dropout_fraction=0.0,
                          n_holes=0)
    noisy = ScannerConfig(n_points=args.points, noise_mm=0.05, outlier_fraction=0.002, dropout_fraction=0.05,
                          n_holes=4, hole_radius_mm=60.0)

    def scan(name: str, settings: dict[str, float], config: ScannerConfig, seed: int):
        print(f"make_bags: {name} {settings}", file=sys.stderr)
        return make_scenario_scan(name, solver, reduced, skin, settings, config, seed)

    labels = reduced.names
    scenarios = {
        "clean": ("Three clean scans at known boundary states.", [
            scan("clean_1", dict(zip(labels, (0.5, -0.3, 0.4, -0.6, 0.2, 0.3), strict=True)), clean, 1),
            scan("clean_2", dict(zip(labels, (-0.8, 0.6, -0.2, 0.7, 0.5, -0.4), strict=True)), clean, 2),
            scan("clean_3", dict(zip(labels, (0.1, 0.9, 0.8, 0.3, -0.1, 0.6), strict=True)), clean, 3),
        ]),
        "noisy_occluded": ("Three scans with 0.05 mm noise, holes, dropouts and outliers; BUFFER_L lowered by 1 mm.", [
            scan("noisy_1", dict(zip(labels, (0.3, 0.2, -0.5, 0.4, -1.0, 0.2), strict=True)), noisy, 4),
            scan("noisy_2", dict(zip(labels, (-0.4, -0.7, 0.6, 0.1, 0.4, -0.3), strict=True)), noisy, 5),
            scan("noisy_3", dict(zip(labels, (0.7, 0.0, 0.0, -0.9, 0.8, 0.5), strict=True)), noisy, 6),
        ]),
        "undeclared": ("Two scans with an undeclared effect: the fixed right hinge moved 0.5 mm in Z.", [
            scan("undeclared_1", {**dict(zip(labels, (0.2, -0.4, 0.3, 0.5, 0.1, 0.2), strict=True)),
                                  "hinge_R.z": 0.5}, clean, 7),
            scan("undeclared_2", {**dict(zip(labels, (-0.5, 0.3, -0.4, 0.2, 0.6, 0.4), strict=True)),
                                  "hinge_R.z": 0.5}, noisy, 8),
        ]),
    }
    good_a = scan("malformed_good_a", dict(zip(labels, (0.4, 0.1, -0.3, 0.2, 0.3, 0.1), strict=True)), clean, 9)
    good_b = scan("malformed_good_b", dict(zip(labels, (-0.2, -0.5, 0.5, -0.1, 0.2, 0.4), strict=True)), clean, 10)
    scenarios["malformed"] = (
        "Every kind of malformed cloud between good scans: " + "; ".join(MALFORMED.values()) + ".",
        [good_a, *[(kind, good_a) for kind in MALFORMED], good_b],
    )
    args.out.mkdir(parents=True, exist_ok=True)
    for name, (description, items) in scenarios.items():
        path = args.out / name
        if path.exists():
            shutil.rmtree(path)
        sidecar = write_scenario_bag(path, items, model_id=model.model_id, resolution=RESOLUTION,
                                     description=description)
        print(f"make_bags: wrote {path} and {sidecar.name}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
