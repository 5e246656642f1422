"""`hood-decomp model`: write a part model (model.yaml + mesh) from a built-in preset."""

from __future__ import annotations

import argparse
import sys

from hood_decomp.cli._common import check_output, written_whole_directory

HELP = "write a part model (model.yaml + mesh.vtu) from a built-in preset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", choices=["hood", "hood-paper"], default="hood",
                        help="built-in model: hood (default; preloaded rubber-pad buffers, effective states) or "
                        "hood-paper (the paper's boundary physics: rigid unilateral buffers, commanded states)")
    parser.add_argument("--resolution", choices=["coarse", "default", "paper"], default="default",
                        help="mesh resolution: coarse (~1.4k nodes, tests), default (~30k skin nodes), "
                        "paper (>= 188,559 skin nodes)")
    parser.add_argument("--out", required=True, help="output directory (gets model.yaml and mesh.vtu)")


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.fe.hood_preset import build_preset
    from hood_decomp.io.model_files import MODEL_FILE, save_model

    out = check_output(args.out, (), directory=True)
    model = build_preset(args.preset, args.resolution)
    with written_whole_directory(out) as temporary:
        save_model(model, temporary)
    path = out / MODEL_FILE
    print(f"wrote {path}: {len(model.nodes)} nodes, {len(model.cells)} shells, {len(model.skin_nodes)} skin nodes, "
          f"parameters {', '.join(model.names)}; model_id {model.model_id}", file=sys.stderr)
    return 0
