"""The shift report's pictures: control charts, capability, correlation between boundaries, share of parts outside
the model over time (PNG through :func:`hood_decomp.plots.figure.save_figure`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hood_decomp.plots.figure import save_figure
from hood_decomp.shift.spc import RULES, Capability, ControlChart

_MARKERS = dict(zip(RULES, ("o", "s", "^", "D", "v"), strict=True))


def plot_control_chart(chart: ControlChart, path: str | Path) -> Path:
    """Individuals chart (values, centre, 1/2/3 sigma zones, baseline shaded, alarms by rule) over the EWMA chart."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5), sharex=True, gridspec_kw={"height_ratios": (2, 1)})
    index = np.arange(chart.values.size)
    top.plot(index, chart.values, "-", color="0.55", lw=0.6)
    top.plot(index, chart.values, ".", color="k", ms=2.5)
    for k, style in ((3, "-"), (2, "--"), (1, ":")):
        for sign in (-1, 1):
            top.axhline(chart.centre + sign * k * chart.sigma, color="tab:red" if k == 3 else "0.6", ls=style, lw=0.8)
    top.axhline(chart.centre, color="tab:green", lw=0.8)
    for ax in (top, bottom):
        ax.axvspan(-0.5, chart.baseline_end - 0.5, color="tab:blue", alpha=0.08, lw=0)
    for rule in RULES[:-1]:
        hits = chart.alarms[rule]
        if hits.size:
            top.plot(hits, chart.values[hits], _MARKERS[rule], mfc="none", mec="tab:red", ms=7,
                     label=f"{rule} ({hits.size})")
    top.set_ylabel(f"{chart.name} (mm)")
    top.set_title(f"{chart.name}: individuals chart, limits from the baseline (shaded)")
    if any(chart.alarms[r].size for r in RULES[:-1]):
        top.legend(fontsize=7, loc="upper left")
    bottom.plot(index, chart.ewma, color="tab:purple", lw=1.0)
    bottom.plot(index, chart.centre + chart.ewma_limit, color="tab:red", lw=0.7)
    bottom.plot(index, chart.centre - chart.ewma_limit, color="tab:red", lw=0.7)
    hits = chart.alarms["ewma"]
    if hits.size:
        bottom.plot(hits, chart.ewma[hits], "v", mfc="none", mec="tab:red", ms=7, label=f"ewma ({hits.size})")
        bottom.legend(fontsize=7, loc="upper left")
    bottom.set_ylabel("EWMA (mm)")
    bottom.set_xlabel("part (time order)")
    return save_figure(fig, path)


def plot_capability(capabilities: Sequence[Capability], path: str | Path) -> Path:
    """Cpk and Ppk per boundary with the usual 1.33 and 1.0 marks."""
    fig, ax = plt.subplots(figsize=(7, 3.2))
    x = np.arange(len(capabilities))
    ax.bar(x - 0.2, [min(c.cpk, 50) for c in capabilities], 0.4, label="Cpk (within)")
    ax.bar(x + 0.2, [min(c.ppk, 50) for c in capabilities], 0.4, label="Ppk (overall)")
    ax.axhline(1.33, color="tab:green", ls="--", lw=0.8)
    ax.axhline(1.0, color="tab:red", ls="--", lw=0.8)
    ax.set_xticks(x, [c.name for c in capabilities], rotation=30)
    ax.set_ylabel("capability index")
    ax.set_title("Capability against the parameter ranges")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_correlation(names: Sequence[str], matrix: np.ndarray, path: str | Path) -> Path:
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    image = ax.imshow(np.nan_to_num(matrix), vmin=-1, vmax=1, cmap="RdBu_r")
    for (i, j), value in np.ndenumerate(matrix):
        ax.text(j, i, "-" if not np.isfinite(value) else f"{value:.2f}", ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right")
    ax.set_yticks(range(len(names)), names)
    fig.colorbar(image, ax=ax, label="correlation")
    ax.set_title("Correlation between boundaries")
    return save_figure(fig, path)


def plot_outside_share(share: np.ndarray, alpha: float, window: int, path: str | Path) -> Path:
    fig, ax = plt.subplots(figsize=(9, 2.8))
    ax.plot(np.arange(share.size), 100 * share, color="tab:orange")
    ax.axhline(100 * alpha, color="0.4", ls="--", lw=0.8, label=f"expected without a missing effect ({alpha:g})")
    ax.set_xlabel("part (time order)")
    ax.set_ylabel("outside the model (%)")
    ax.set_title(f"Share of parts outside the model, last {window} parts")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_amplitudes(name: str, index: np.ndarray, amplitude: np.ndarray, std: np.ndarray, unit: str,
                    path: str | Path) -> Path:
    fig, ax = plt.subplots(figsize=(9, 2.8))
    ax.errorbar(index, amplitude, yerr=std, fmt=".", ms=3, lw=0.6)
    ax.set_xlabel("part (time order)")
    ax.set_ylabel(f"amplitude ({unit})")
    ax.set_title(f"{name}: amplitude per part")
    return save_figure(fig, path)
