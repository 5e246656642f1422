"""`hood-decomp launch`: start the scan, estimator and decomposition nodes as separate processes."""

from __future__ import annotations

import argparse
import pathlib
import sys

from hood_decomp.ros.launcher import NODE_EXECUTABLES, bring_up, run_until_interrupted, start_nodes

HELP = "start the three nodes as separate processes and bring them to active (Ctrl-C stops them)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bases", required=True, type=pathlib.Path, help="bases file (hood-decomp bases --out)")
    parser.add_argument("--params", type=pathlib.Path, help="ROS parameter YAML file (see config/hood_decomp.yaml)")
    parser.add_argument("--nodes", nargs="+", choices=NODE_EXECUTABLES, default=list(NODE_EXECUTABLES),
                        help="which nodes to start (default: all three)")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.io.bases import load_bases

    load_bases(args.bases)  # a bad bases file is refused here, not in three node logs
    processes = start_nodes(args.bases.resolve(), params_file=args.params, nodes=args.nodes, activate=False)
    print(f"hood-decomp launch: started {', '.join(args.nodes)} (pids "
          f"{', '.join(str(p.pid) for p in processes)}); bringing them to active", file=sys.stderr)
    failures = bring_up(args.nodes, processes=processes)
    for name in args.nodes:
        state = f"NOT ACTIVE: {failures[name]}" if name in failures else "active"
        print(f"hood-decomp launch: {name} {state}", file=sys.stderr)
    print("hood-decomp launch: Ctrl-C stops the nodes", file=sys.stderr)
    return max(run_until_interrupted(processes), 1 if failures else 0)
