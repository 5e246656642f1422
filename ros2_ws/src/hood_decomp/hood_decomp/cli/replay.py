"""`hood-decomp replay BAG [--record OUT_BAG]`: run the three nodes on a recorded bag."""

from __future__ import annotations

import argparse
import pathlib
import sys
import tempfile

from hood_decomp.cli._common import check_output, finite, write_json
from hood_decomp.errors import BagError

HELP = "publish a bag's scans into the nodes (started here with --bases) and record what they publish"
LOG_FORMAT = "hood-decomp replay: %(message)s"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=pathlib.Path, help="rosbag2 directory with sensor_msgs/PointCloud2 on scan/points")
    parser.add_argument("--record", type=pathlib.Path, help="new bag directory for everything the nodes publish")
    parser.add_argument("--bases", type=pathlib.Path,
                        help="start the three nodes with this bases file (else they must be running already)")
    parser.add_argument("--params", type=pathlib.Path, help="ROS parameter YAML for the nodes started here (applied "
                        "after the cell calibration the bag's sidecar states)")
    parser.add_argument("--timeout", type=finite(0.0, 86400.0, low_open=True), default=60.0,
                        help="longest wait for one scan's answer, s")
    parser.add_argument("--clock", action="store_true", help="publish each scan's bag time on /clock")
    parser.add_argument("--json", type=pathlib.Path, help="write the replay summary as JSON")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.ros.launcher import start_nodes, stop_nodes
    from hood_decomp.ros.replay import replay_bag

    inputs = [p for p in (args.bag, args.bases, args.params) if p is not None]
    if args.record is not None:
        if args.record.exists():
            raise BagError(f"--record {args.record} exists; a recording goes to a new bag directory")
        check_output(args.record, inputs, "--record", directory=True)
    if args.json is not None:
        check_output(args.json, inputs, "--json")
    if args.bases is not None:
        from hood_decomp.io.bases import load_bases

        load_bases(args.bases)  # a bad bases file is refused here, not in three node logs
    processes = []
    with tempfile.TemporaryDirectory(prefix="hood_decomp_replay_") as scratch:
        if args.bases is not None:
            files = [p for p in (sidecar_params(args.bag, pathlib.Path(scratch)), args.params) if p is not None]
            processes = start_nodes(args.bases.resolve(), params_file=files)
        try:
            result = replay_bag(args.bag, record=args.record, timeout_s=args.timeout, publish_clock=args.clock,
                                part=sidecar_part(args.bag))
        finally:
            stop_nodes(processes)
    summary = {"scans": result.scans, "answered": result.answered, "refused": result.refused,
               "unanswered": result.unanswered, "recorded": result.recorded, "seconds": round(result.seconds, 2),
               "record": str(args.record) if args.record else None, "inspection": result.inspection or None}
    if args.json:
        write_json(args.json, summary)
    if result.inspection:
        print(f"hood-decomp replay: part {result.inspection['part_id']}: {result.inspection['message']}",
              file=sys.stderr)
    for stamp, reasons in result.refused.items():
        print(f"hood-decomp replay: scan {stamp} refused: {reasons[0]}", file=sys.stderr)
    for stamp in result.unanswered:
        print(f"hood-decomp replay: scan {stamp} unanswered within {args.timeout:g} s", file=sys.stderr)
    print(f"hood-decomp replay: {result.scans} scans, {result.answered} answered, {len(result.refused)} refused, "
          f"{len(result.unanswered)} unanswered, {result.recorded} messages recorded"
          + (f" in {args.record}" if args.record else ""), file=sys.stderr)
    return 1 if result.unanswered or result.refused else 0


def _sidecar(bag: pathlib.Path) -> dict:
    from hood_decomp.io.bags import read_sidecar, sidecar_path

    return read_sidecar(bag) if sidecar_path(bag).is_file() else {}


def sidecar_part(bag: pathlib.Path):
    """The multi-view part the bag's sidecar names (``part_id`` and ``expected_views``: a robot's views of one part,
    replayed as one InspectPart), or None (every cloud is a part of its own)."""
    from hood_decomp.ros.replay import ReplayPart

    sidecar = _sidecar(bag)
    if "part_id" not in sidecar or "expected_views" not in sidecar:
        return None
    part_id, views = sidecar["part_id"], sidecar["expected_views"]
    if not isinstance(part_id, str) or isinstance(views, bool) or not isinstance(views, int) or not 1 <= views <= 1000:
        raise BagError(f"sidecar of {bag}: part_id must be text and expected_views a whole number 1..1000, got "
                       f"{part_id!r} and {views!r}")
    return ReplayPart(part_id, views)


def sidecar_params(bag: pathlib.Path, directory: pathlib.Path) -> pathlib.Path | None:
    """The cell calibration (scanner pose, reference markers) the bag's sidecar states, as a parameter file for the
    scan node; None when the bag has no sidecar or it states neither (the nodes then use --params). A multi-view
    bag states markers without a fixed scanner pose (each view's pose comes from the bag's TF and scan/pose)."""
    import numpy as np

    from hood_decomp.ros.scan_bag import write_node_params

    sidecar = _sidecar(bag)
    if "scanner_pose_mm" not in sidecar and "marker_positions_mm" not in sidecar:
        return None
    if "scanner_pose_mm" not in sidecar:
        sidecar = {**sidecar, "scanner_pose_mm": np.eye(4).tolist()}  # the identity: no fixed pose
    try:
        return write_node_params(directory / "sidecar_params.yaml", sidecar)
    except (AttributeError, KeyError, TypeError, ValueError) as error:
        raise BagError(f"sidecar of {bag}: the scanner pose or marker positions are malformed ({error})") from error
