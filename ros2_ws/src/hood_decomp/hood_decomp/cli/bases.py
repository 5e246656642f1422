"""`hood-decomp bases`: build the PCA and hierarchical bases from an ensemble (section 3.1.2)."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from hood_decomp.errors import EnsembleError

HELP = "build the PCA and hierarchical bases from an ensemble"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ensemble", required=True, type=Path, help="ensemble store written by `hood-decomp ensemble`")
    parser.add_argument("--out", required=True, type=Path, help="bases file to write (HDF5, .h5)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--components", type=int, default=None,
                       help="number of PCA components (default 10; fewer when the ensemble supports fewer)")
    group.add_argument("--explained-variance", type=float, default=None,
                       help="choose the PCA components by cumulative explained variance instead, e.g. 0.999999")
    parser.add_argument("--epsilon", type=float, default=0.1,
                        help="hierarchical tolerance: max allowed member error, mm (default 0.1, the paper's)")
    parser.add_argument("--model", type=Path, default=None,
                        help="model directory: its reduced FE model goes into the bases file for the contact-aware "
                        "estimator (needed unless the ensemble store holds one)")
    parser.add_argument("--plots", type=Path, default=None, help="directory for the explained-variance plot (Fig. 8)")


def load_training_set(path: Path, model_dir: Path | None, say):
    """(training Ensemble, SkinSurface, ReducedModel or None) from the ensemble store (and the model directory)."""
    from hood_decomp.io.ensemble_store import load_ensemble, load_skin

    ensemble, skin = load_ensemble(path, "training"), load_skin(path)
    store = importlib.import_module("hood_decomp.io.ensemble_store")
    if hasattr(store, "load_reduced_model"):
        reduced = store.load_reduced_model(path)
        if reduced is not None:
            return ensemble, skin, reduced
    if model_dir is None:
        say("bases: no --model and no reduced model in the store: only the paper's 'pca' estimator will be available")
        return ensemble, skin, None
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.io.model_files import load_model

    model = load_model(model_dir)
    if model.model_id != ensemble.model_id:
        raise EnsembleError(
            f"model {model_dir} (model_id {model.model_id}) is not the ensemble's ({ensemble.model_id})")
    return ensemble, skin, reduce_model(build_solver(model, progress=say))


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.method.bases import build_bases
    from hood_decomp.io.bases import save_bases

    def say(text: str) -> None:
        print(text, file=sys.stderr)

    ensemble, skin, reduced = load_training_set(args.ensemble, args.model, say)
    components = 10 if args.components is None and args.explained_variance is None else args.components
    bases = build_bases(ensemble, skin, reduced, components, args.explained_variance, args.epsilon, progress=say)
    save_bases(args.out, bases)
    if args.plots is not None:
        from hood_decomp.plots.method import plot_explained_variance

        plot_explained_variance(bases.pca.explained_variance_ratio_, args.plots / "explained_variance.png")
    print(f"wrote {args.out}: {bases.pca.n_components_} PCA components, "
          f"{len(bases.hierarchical.effect_names_)} hierarchical effects at epsilon {args.epsilon} mm, "
          f"reduced model {'included' if reduced is not None else 'absent'}")
    return 0
