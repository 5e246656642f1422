"""Write the scenario bags of bags/ (rosbag2 MCAP via rosbags) with their truth sidecars; rebuild them with

    scripts/with-env python scripts/make_bags.py [--out bags] [--points 40000] [--only NAME ...]

Scenarios on the built-in hood at default resolution (the coarse grid's 30 mm node spacing is too coarse for a
scan-derived field to stay within the scan noise; the tests rebuild the same model and check its model_id against
the sidecar):
- clean: three scans at known boundary states, 0.005 mm noise, no occlusion.
- noisy_occluded: three scans with 0.05 mm noise, dropout holes, outliers and a lifted buffer.
- undeclared: two scans whose part has an effect the model does not declare (the fixed right hinge moved in Z).
- malformed: every kind of broken cloud of hood_decomp.ros.scan_bag.MALFORMED between two good scans.
- multiview: one part in four partial views from a robot (/tf_static, /tf and scan/pose carry the robot's poses;
  view 3's pose is 2 mm / 0.2 deg off, its markers correct it), for an InspectPart of four views.
"""

from __future__ import annotations

import argparse
import pathlib
import shutil
import sys

import numpy as np

from hood_decomp.core.fe.hood_preset import build_hood
from hood_decomp.core.fe.model import skin_surface
from hood_decomp.core.fe.solver import build_solver, reduce_model
from hood_decomp.core.scan.registration import rotation_from_vector
from hood_decomp.ros.scan_bag import MALFORMED, write_multiview_bag, write_scenario_bag
from hood_decomp.synthetic.scanner import ScannerConfig, random_rigid
from hood_decomp.synthetic.scenarios import make_scenario_scan

RESOLUTION = "default"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path(__file__).parents[1] / "bags")
    parser.add_argument("--points", type=int, default=80_000, help="scan points per cloud (keeps bags/ small)")
    parser.add_argument("--only", nargs="+", default=None, help="write only these bags")
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
    if args.only is None or "multiview" in args.only:
        write_multiview(args.out / "multiview", scan, labels, model.model_id, args.points)
    for name, (description, items) in scenarios.items():
        if args.only is not None and name not in args.only:
            continue
        path = args.out / name
        if path.exists():
            shutil.rmtree(path)
        sidecar = write_scenario_bag(path, items, model_id=model.model_id, resolution=RESOLUTION,
                                     description=description)
        print(f"make_bags: wrote {path} and {sidecar.name}", file=sys.stderr)
    return 0


#: the multi-view bag's views: aim (fractions of the half extents) and tilt (deg) of each robot pose
MULTIVIEW = (((-0.55, -0.45), (12.0, -12.0)), ((0.55, -0.45), (12.0, 12.0)), ((-0.55, 0.5), (-12.0, -12.0)),
             ((0.55, 0.5), (-12.0, 12.0)))


def write_multiview(path: pathlib.Path, scan, labels, model_id: str, points: int) -> None:
    """One part (a state inside the ranges) in four partial views; the robot reports each scanner pose 0.05 mm /
    0.005 deg off the truth, view 3 2 mm / 0.2 deg off."""
    settings = dict(zip(labels, (0.3, -0.4, 0.5, -0.2, 0.4, 0.3), strict=True))
    rng = np.random.default_rng(17)
    views, robot = [], []
    for k, (aim, tilt) in enumerate(MULTIVIEW):
        config = ScannerConfig(n_points=points, noise_mm=0.02, marker_noise_mm=0.01, n_holes=1, view_center=aim,
                               view_tilt_deg=tilt, fov_deg=40.0, standoff_mm=1500.0, pose_error_deg=0.0,
                               pose_error_mm=0.0)
        view = scan(f"multiview_{k + 1}", settings, config, 20 + k)
        views.append(view)
        robot.append(view.scan.true_transform @ random_rigid(rng, *((0.2, 2.0) if k == 2 else (0.005, 0.05))))
    base = np.eye(4)
    base[:3, 3] = [-1200.0, 0.0, -400.0]
    hand_eye = np.eye(4)
    hand_eye[:3, :3] = rotation_from_vector(np.radians([0.0, 0.0, 90.0]))
    hand_eye[:3, 3] = [0.0, 60.0, 150.0]
    if path.exists():
        shutil.rmtree(path)
    sidecar = write_multiview_bag(
        path, views, robot, part_id="hood-multiview-1", model_id=model_id, resolution=RESOLUTION, base_pose_mm=base,
        hand_eye_mm=hand_eye, description="One part in four partial views from a robot: /tf_static (part <- robot "
        "base, flange <- scanner), /tf (base <- flange around each cloud), scan/pose (part <- scanner); the robot "
        "reports view 3 2 mm / 0.2 deg off its true pose (its markers correct it).")
    print(f"make_bags: wrote {path} and {sidecar.name}", file=sys.stderr)


if __name__ == "__main__":
    raise SystemExit(main())
