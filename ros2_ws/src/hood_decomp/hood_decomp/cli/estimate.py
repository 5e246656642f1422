"""`hood-decomp estimate`: estimate the parameter states of a field or scan (eqs. 4-5, contact-aware by default)."""

from __future__ import annotations

import argparse

from hood_decomp.cli._common import (
    add_bases,
    add_inputs,
    add_json,
    add_reference,
    check_json,
    emit_json,
    finite,
    marker_checks_or_none,
    read_bases_and_field,
)

HELP = "estimate the parameter states of a field or scan"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_bases(parser)
    add_inputs(parser)
    add_json(parser)
    add_reference(parser)
    parser.add_argument("--temperature-k", type=finite(-100.0, 100.0), default=0.0, metavar="K",
                        help="part temperature minus the model's reference temperature, K (default 0; needs "
                        "calibrated bases, which carry the thermal response)")
    parser.add_argument("--method", choices=("contact", "pca"), default="contact",
                        help="contact-aware estimator (default) or the paper's PCA estimator")
    parser.add_argument("--components", choices=("normal", "xyz"), default="normal",
                        help="displacement components fitted: normal (default; a scan measures normal distances) or "
                        "xyz, all three, as the paper does (a field file with a 3D displacement, e.g. from "
                        "`simulate`, and no error model; the within-model test then judges each component)")
    parser.add_argument("--coarsen", type=coarsening, default="auto", metavar="auto|STRIDE",
                        help="the paper's coarsening of the input field: fit and test it on one node per cell of "
                        "STRIDE node spacings (1: every node); auto (default): a quarter of the nodes of a scan's "
                        "field on a skin of more than 100,000 nodes fitted on its normal component (the paper-"
                        "resolution hood), every node otherwise (a white or simulated field would lose precision)")


def coarsening(text: str) -> int | str:
    """``--coarsen``'s value (:func:`~hood_decomp.core.method.coarsening.parse_coarsening`; argparse names anything
    else, exit 2)."""
    from hood_decomp.core.method.coarsening import parse_coarsening
    from hood_decomp.errors import BasisError

    try:
        return parse_coarsening(text)
    except BasisError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def estimate_payload(estimate, n_bilateral: int) -> dict:
    """What `estimate` writes: per parameter the state and its std (mm, null when unknown), the full covariance
    (``covariance_mm2``: label -> label -> mm^2; the measurement's), what the model's physical factors, not calibrated
    to the part, add apart from it (core.method.model_spread: ``model_std_mm``, ``model_covariance_mm2`` and
    ``model_factors_mm``: factor -> label -> one-sigma effect, mm; null for the "pca" method), ``lifted`` for the
    unilateral boundaries, residual RMS and max (mm), coverage, ``weighting`` ("generalised": least squares weighted
    by the field's error model, registration included; "ordinary": a field without one), within_model with the one
    test behind it (``within_model_test``: p_value, alpha, statistic, dof, noise_scale, noise_source: "residual" when
    the field states no error model and the noise level is estimated from the residual with ``denominator_dof``
    degrees of freedom), method and ``components`` ("normal" or "xyz": the displacement components fitted; for
    "xyz" the residual RMS and max are still the normal residual's). ``measured_effects`` names the parameters without
    a boundary (measured effects: their value is an amplitude); ``correction`` is what the estimator node would send
    the robot with the default policy
    (core.method.correction.plan_correction: the move per boundary, mm, never one for a measured effect or a lifted
    buffer; safe_to_apply, applicable, reason)."""
    from hood_decomp.core.method.correction import plan_correction

    names = estimate.names
    correction = plan_correction(estimate)
    covariance = estimate.covariance
    check = estimate.check
    return {
        "parameters_mm": dict(zip(names, estimate.values, strict=True)),
        "std_mm": dict(zip(names, estimate.std, strict=True)),
        "covariance_mm2": None if covariance is None else {
            row: dict(zip(names, covariance[i], strict=True)) for i, row in enumerate(names)},
        "model_std_mm": None if estimate.model_std is None else dict(zip(names, estimate.model_std, strict=True)),
        "model_covariance_mm2": None if estimate.model_effects is None else {
            row: dict(zip(names, estimate.model_covariance[i], strict=True)) for i, row in enumerate(names)},
        "model_factors_mm": None if estimate.model_effects is None else {
            factor: dict(zip(names, effect, strict=True))
            for factor, effect in zip(estimate.model_factors, estimate.model_effects, strict=True)},
        "within_model_test": None if check is None else {
            "p_value": check.p_value, "alpha": check.alpha, "statistic": check.statistic, "dof": check.dof,
            "denominator_dof": check.denominator_dof, "noise_scale": check.noise_scale,
            "noise_source": check.noise_source, "effective_samples": check.n_effective},
        "lifted": dict(zip(names[n_bilateral:], estimate.lifted[n_bilateral:], strict=True)),
        "residual_rms_mm": estimate.residual_rms,
        "residual_max_mm": estimate.residual_max,
        "coverage": estimate.coverage,
        "within_model": estimate.within_model,
        "method": estimate.method,
        "weighting": estimate.weighting,
        "components": estimate.components,
        "measured_effects": [name for name, boundary in zip(names, estimate.boundary, strict=True) if not boundary],
        "correction": {
            "corrections_mm": dict(zip(names, correction.corrections, strict=True)),
            "applicable": dict(zip(names, correction.applicable, strict=True)),
            "safe_to_apply": correction.safe_to_apply, "reason": correction.reason},
    }


def zones_payload(verdicts) -> dict:
    """The tolerance zones' verdicts (core.method.tolerance.zone_verdicts) as `estimate` writes them: ``zones`` (per
    zone name, ok, lower_mm, upper_mm, worst_deviation_mm, worst_node, coverage, outside, reason) and ``zones_ok``."""
    import dataclasses

    return {"zones": [dataclasses.asdict(verdict) for verdict in verdicts],
            "zones_ok": all(verdict.ok for verdict in verdicts)}


def run(args: argparse.Namespace) -> int:
    from hood_decomp.core.method.bases import estimate_field
    from hood_decomp.core.method.coarsening import coarsening_stride
    from hood_decomp.core.method.tolerance import zone_verdicts
    from hood_decomp.io.bases import bases_provenance

    check_json(args)
    # the estimator is fitted (0.1-0.4 s at paper resolution), and for a scan its reading's gradients made (0.2 s),
    # while the scan is read and turned into a field
    checks: list[dict] = []
    scan = any(kind == "scan" for kind, _ in args.inputs)
    bases, field = read_bases_and_field(args, lambda bases: bases.prepare_estimation(
        args.method, args.min_coverage, args.temperature_k, args.components, scan, args.coarsen), marker_checks=checks)
    estimate = estimate_field(bases, field, args.method, args.min_coverage, args.temperature_k, args.components,
                              args.coarsen)
    payload = estimate_payload(estimate, bases.pca.n_bilateral_)
    stride = coarsening_stride(args.coarsen, bases.skin.n_nodes, args.components, field.errors)
    payload["coarsening"] = {"stride": stride, "fitted_nodes": int(
        bases.coarsened(stride).nodes.size if stride > 1 else bases.skin.n_nodes), "nodes": bases.skin.n_nodes}
    payload.update(bases_provenance(bases), reference=None if args.reference is None else str(args.reference),
                   temperature_k=args.temperature_k, marker_noise_checks=marker_checks_or_none(args, checks))
    payload.update(zones_payload(zone_verdicts(field, bases.tolerance_zones)))
    emit_json(payload, args.json)
    return 0
