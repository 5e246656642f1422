"""PNG figures of closing the loop: residual maps before/after (plan view, shared colour scale, via
:func:`hood_decomp.plots.method.plot_skin_field`) and a before/after bar chart of residuals and parameter errors."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hood_decomp.core.loop.close_loop import CloseLoopResult
from hood_decomp.core.types import SkinSurface
from hood_decomp.plots.figure import save_figure
from hood_decomp.plots.method import plot_skin_field


def plot_residual_maps(skin: SkinSurface, result: CloseLoopResult, out_dir: str | Path) -> list[Path]:
    """residual_before_<i>.png and (when an effect was added) residual_after_<i>.png per field, signed residual in mm
    on one symmetric colour scale per field (the before residual's largest |r|), so the two maps compare directly."""
    out_dir = Path(out_dir)
    paths = []
    for i, before in enumerate(result.analyses_before):
        top = max(before.max_mm, 1e-9)
        levels = np.linspace(-top, top, 21)
        region = f"; {len(before.regions)} region(s) beyond noise" if before.regions else ""
        paths.append(plot_skin_field(
            skin, before.residual, out_dir / f"residual_before_{i}.png",
            f"field {i}: residual before, RMS {before.rms_mm:.4f} mm{region}", "residual (mm)", levels, "RdBu_r"))
        if result.analyses_after:
            after = result.analyses_after[i]
            added = ", ".join(a.name for a in result.added)
            paths.append(plot_skin_field(
                skin, after.residual, out_dir / f"residual_after_{i}.png",
                f"field {i}: residual with {added}, RMS {after.rms_mm:.4f} mm", "residual (mm)", levels, "RdBu_r"))
    return paths


def plot_before_after(result: CloseLoopResult, path: str | Path,
                      truth: Sequence[Mapping[str, float]] | None = None) -> Path:
    """Bar chart: residual RMS and max per field before/after (left); per parameter the largest |error| over the
    fields before/after when ``truth`` is given, else the largest |estimate| (right). Lifted pads are left out of
    the errors (their value is the part's position, not the commanded one)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [1, 2]})
    n = len(result.analyses_before)
    x = np.arange(n)
    after = result.analyses_after or ()
    width = 0.2
    left.bar(x - 1.5 * width, [a.rms_mm for a in result.analyses_before], width, label="RMS before", color="tab:red")
    left.bar(x - 0.5 * width, [a.max_mm for a in result.analyses_before], width, label="max before", color="salmon")
    if after:
        left.bar(x + 0.5 * width, [a.rms_mm for a in after], width, label="RMS after", color="tab:green")
        left.bar(x + 1.5 * width, [a.max_mm for a in after], width, label="max after", color="lightgreen")
    left.plot(x, [a.noise_mm for a in result.analyses_before], "k_", markersize=30, label="scan noise")
    left.set_xticks(x, [f"field {i}" for i in range(n)])
    left.set_yscale("log")
    left.set_ylabel("residual (mm)")
    left.legend(fontsize=7)

    names = list(result.after[0].names if result.after else result.before[0].names)

    def largest(estimates: Sequence, name: str) -> float:
        values = []
        for i, estimate in enumerate(estimates):
            if name not in estimate.names:
                continue
            j = estimate.names.index(name)
            if truth is None:
                values.append(abs(estimate.values[j]))
            elif name in truth[i] and not estimate.lifted[j]:
                values.append(abs(estimate.values[j] - truth[i][name]))
        return max(values) if values else np.nan

    x = np.arange(len(names))
    right.bar(x - 0.2, [largest(result.before, n_) for n_ in names], 0.4, label="before", color="tab:red")
    if result.after:
        right.bar(x + 0.2, [largest(result.after, n_) for n_ in names], 0.4, label="after", color="tab:green")
    right.set_xticks(x, names, rotation=30, ha="right")
    right.set_yscale("log")
    right.set_ylabel("|estimate - truth| (mm or N)" if truth is not None else "|estimate| (mm or N)")
    right.legend()
    fig.suptitle(result.message[:140], fontsize=9)
    return save_figure(fig, path)
