"""`hood-decomp bases`: build the PCA and hierarchical bases from an ensemble (section 3.1.2)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from hood_decomp.cli._common import check_output, finite, model_inputs, written_whole
from hood_decomp.core.method.hierarchical import SPANS
from hood_decomp.errors import EnsembleError

if TYPE_CHECKING:
    from hood_decomp.core.method.model_spread import PhysicalResponses
    from hood_decomp.core.types import ReducedModel, ToleranceZone

HELP = "build the PCA and hierarchical bases from an ensemble"

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ensemble", required=True, type=Path, help="ensemble store written by `hood-decomp ensemble`")
    parser.add_argument("--out", required=True, type=Path, help="bases file to write (HDF5, .h5)")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--components", type=finite(1, 1000, integer=True), default=None,
                       help="number of PCA components (default 10; fewer when the ensemble supports fewer)")
    group.add_argument("--explained-variance", type=finite(0.0, 1.0, low_open=True), default=None,
                       help="choose the PCA components by cumulative explained variance instead, e.g. 0.999999")
    parser.add_argument("--epsilon", type=finite(0.0, 100.0, low_open=True, why=" mm: the tolerance of a member "
                        "error; 100 mm is beyond any sheet-metal deviation"), default=0.1,
                        help="hierarchical tolerance: max allowed member error, mm (default 0.1, the paper's)")
    parser.add_argument("--span", choices=SPANS, default="whole",
                        help="span a member is measured against in the hierarchical greedy: whole (the paper's Fig. 5, "
                        "every effect found so far; default) or subset (the effects of its own parameters, what "
                        "decomposition step 3 leaves for such a field)")
    parser.add_argument("--model", type=Path, default=None,
                        help="model directory of the ensemble: its reduced FE model goes into the bases file for the "
                        "contact-aware estimator (without it only the paper's 'pca' estimator is available), with its "
                        "responses to the physical factors (gas springs, 1 K, sheet thickness: one more factorisation "
                        "per sheet group), and its tolerance_zones (acceptance criteria on the skin, "
                        "docs/bases_schema.md)")
    parser.add_argument("--plots", type=Path, default=None, help="directory for the explained-variance plot (Fig. 8)")


def _reduced_model(model_dir: Path | None, model_id: str
                   ) -> tuple[ReducedModel | None, PhysicalResponses | None, tuple[ToleranceZone, ...]]:
    """The ReducedModel, its FE responses to the physical factors (core.loop.calibration.model_physics: an estimate
    from the file considers all five factors) and the tolerance zones of the model in ``model_dir`` (None, None and
    none without one); EnsembleError when it is not the ensemble's model (``model_id``)."""
    if model_dir is None:
        logger.warning("bases: no --model: only the paper's 'pca' estimator will be available")
        return None, None, ()
    from hood_decomp.core.fe.solver import build_solver, reduce_model
    from hood_decomp.core.loop.calibration import model_physics
    from hood_decomp.io.model_files import load_model_with_zones

    model, zones = load_model_with_zones(model_dir)
    if model.model_id != model_id:
        raise EnsembleError(f"model {model_dir} (model_id {model.model_id}) is not the ensemble's ({model_id})")
    solver = build_solver(model)
    reduced = reduce_model(solver)
    logger.info("bases: the model's responses to gas springs, 1 K and sheet thickness (one factorisation per group)")
    return reduced, model_physics(model, reduced, solver), zones


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.method.bases import build_bases
    from hood_decomp.io.bases import save_bases
    from hood_decomp.io.ensemble_store import load_ensemble, load_skin

    inputs = [args.ensemble, *(model_inputs(args.model) if args.model is not None else ())]
    out = check_output(args.out, inputs)
    if args.plots is not None:
        check_output(args.plots, inputs, "--plots", directory=True, writes=["explained_variance.png"])
    ensemble, skin = load_ensemble(args.ensemble, "training"), load_skin(args.ensemble)
    reduced, physics, zones = _reduced_model(args.model, ensemble.model_id)
    components = 10 if args.components is None and args.explained_variance is None else args.components
    bases = dataclasses.replace(build_bases(ensemble, skin, reduced, components, args.explained_variance, args.epsilon,
                                            args.span),
                                tolerance_zones=zones, physics=physics)
    with written_whole(out) as temporary:
        save_bases(temporary, bases)
    if args.plots is not None:
        from hood_decomp.plots.method import plot_explained_variance

        plot_explained_variance(bases.pca.explained_variance_ratio_, args.plots / "explained_variance.png")
    print(f"wrote {args.out}: {bases.pca.n_components_} PCA components, "
          f"{len(bases.hierarchical.effect_names_)} hierarchical effects at epsilon {args.epsilon} mm, "
          f"reduced model {'included with its physical responses' if reduced is not None else 'absent'}, "
          f"{len(zones)} tolerance zone(s)")
    return 0
