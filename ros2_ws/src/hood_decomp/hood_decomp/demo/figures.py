"""Pictures of the demo report that are not the method's own plots (those are in plots.method): the model with
its labelled boundaries, estimated-versus-true bars, and the timing comparison with the paper's Table 3."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hood_decomp.core.fe.model import PartModel, patch_nodes
from hood_decomp.plots.figure import save_figure

KIND_COLOURS = {"fixed": "black", "prescribed": "tab:blue", "unilateral": "tab:green", "force": "tab:red"}


def plot_model(model: PartModel, path: str | Path) -> Path:
    """Plan view of every part's mesh and each boundary's patch, coloured by kind and labelled with its name and the
    parameters acting on it (Fig. 7, right)."""
    fig, ax = plt.subplots(figsize=(9, 7))
    for index, part in enumerate(model.parts):
        cells = model.cells[model.cell_part == index]
        xy = model.nodes[cells][:, :, :2]
        closed = np.concatenate([xy, xy[:, :1]], axis=1)
        style = dict(color="0.75", linewidth=0.3) if part.name == model.skin_part else dict(linewidth=0.6)
        lines = ax.plot(closed[:, :, 0].T, closed[:, :, 1].T, **style)
        if part.name != model.skin_part:
            for line in lines:
                line.set_color(plt.get_cmap("tab10")(3 + index % 6))
    params_of: dict[str, list[str]] = {}
    for parameter in model.parameters:
        params_of.setdefault(parameter.boundary, []).append(parameter.label)
    for boundary in model.boundaries:
        nodes = model.nodes[patch_nodes(model, boundary)]
        colour = KIND_COLOURS.get(boundary.kind, "purple")
        ax.scatter(nodes[:, 0], nodes[:, 1], s=14, color=colour, zorder=3)
        label = boundary.name + (f"\n({', '.join(params_of[boundary.name])})" if boundary.name in params_of else "")
        ax.annotate(label, nodes[:, :2].mean(axis=0), xytext=(8, 8), textcoords="offset points", fontsize=8,
                    color=colour, zorder=4, bbox=dict(boxstyle="round", fc="white", alpha=0.8, ec=colour))
    for kind, colour in KIND_COLOURS.items():
        ax.scatter([], [], color=colour, label=kind)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), title="boundary kind")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"{model.name}: {len(model.nodes):,} nodes, {len(model.cells):,} shell elements, "
                 f"{len(model.skin_nodes):,} visible skin nodes")
    return save_figure(fig, path)


def plot_estimate_bars(names: Sequence[str], truth: Sequence[float], estimate: Sequence[float],
                       std: Sequence[float], path: str | Path, title: str) -> Path:
    """True and estimated parameter states side by side, mm, with the estimate's 1-sigma error bar."""
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.bar(x - 0.2, truth, 0.4, label="true", color="0.6")
    ax.bar(x + 0.2, estimate, 0.4, yerr=std, label="estimated", color="tab:blue", capsize=3)
    ax.set_xticks(x, names, rotation=20)
    ax.axhline(0.0, color="k", linewidth=0.5)
    ax.set_ylabel("parameter state (mm)")
    ax.set_title(title)
    ax.legend()
    return save_figure(fig, path)


def plot_timings(rows: Sequence[tuple[str, float, float | None]], path: str | Path) -> Path:
    """Horizontal log-scale bars: (task, our seconds, paper seconds or None)."""
    labels = [r[0] for r in rows]
    y = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(8, 0.5 * len(rows) + 1.5))
    ax.barh(y + 0.2, [max(r[1], 1e-4) for r in rows], 0.4, label="hood_decomp", color="tab:green")
    ax.barh(y - 0.2, [r[2] if r[2] else 0 for r in rows], 0.4, label="paper (Table 3)", color="tab:gray")
    ax.set_yticks(y, labels)
    ax.set_xscale("log")
    ax.set_xlabel("seconds (log scale)")
    ax.legend()
    return save_figure(fig, path)
