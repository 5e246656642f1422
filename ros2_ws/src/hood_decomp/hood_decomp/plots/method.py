"""PNG plots of the method in the paper's style (matplotlib, Agg backend: no display needed).

Skin fields are drawn on the skin triangles in plan view (x, y), mm. Contribution plots (Fig. 11): discrete colour
map 0-100 % in 10 % bands with iso-lines. Explained variance (Fig. 8), estimation-error box plots (Fig. 9) and
maximum-error histograms (Fig. 10), the interaction map of every parameter pair and sign as a heat map.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import matplotlib.tri as mtri
import numpy as np

from hood_decomp.core.method.interactions import InteractionMap
from hood_decomp.core.types import Decomposition, SkinSurface
from hood_decomp.plots.figure import save_figure

_CONTRIBUTION_LEVELS = np.linspace(0.0, 100.0, 11)


def _triangulation(skin: SkinSurface, values: np.ndarray) -> mtri.Triangulation:
    """Plan-view triangulation; triangles touching an unseen (NaN) node are masked."""
    tri = mtri.Triangulation(skin.points[:, 0], skin.points[:, 1], skin.triangles)
    tri.set_mask(np.any(~np.isfinite(values)[skin.triangles], axis=1))
    return tri


def plot_skin_field(
    skin: SkinSurface, values: np.ndarray, path: str | Path, title: str, label: str = "mm",
    levels: Sequence[float] | None = None, cmap: str = "viridis",
) -> Path:
    """One scalar skin field (N,) as filled contours with iso-lines, e.g. a reconstruction-error map."""
    values = np.asarray(values, dtype=float)
    tri = _triangulation(skin, values)
    shown = np.nan_to_num(values)
    if levels is None:
        top = float(np.nanmax(values)) if np.any(np.isfinite(values)) else 1.0
        bottom = float(np.nanmin(values)) if np.any(np.isfinite(values)) else 0.0
        levels = np.linspace(bottom, top if top > bottom else bottom + 1e-12, 11)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    filled = ax.tricontourf(tri, shown, levels=levels, cmap=cmap, extend="both")
    ax.tricontour(tri, shown, levels=levels, colors="k", linewidths=0.5)
    fig.colorbar(filled, ax=ax, label=label)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title)
    return save_figure(fig, path)


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", name).strip("_").lower() or "effect"


def plot_contributions(skin: SkinSurface, decomposition: Decomposition, out_dir: str | Path) -> list[Path]:
    """One PNG per effect: contribution d_i / D (eq. 8) in %, 10 % bands; plus ``reconstruction_error.png``."""
    out_dir = Path(out_dir)
    paths = []
    for index, effect in enumerate(decomposition.effects):
        paths.append(plot_skin_field(
            skin, 100.0 * effect.contribution, out_dir / f"contribution_{index:02d}_{_slug(effect.name)}.png",
            f"Contribution of {effect.name} (share {100 * effect.share:.1f} %)", "contribution (%)",
            _CONTRIBUTION_LEVELS, plt.get_cmap("jet", 10),
        ))
    error = np.abs(decomposition.residual)
    paths.append(plot_skin_field(
        skin, error, out_dir / "reconstruction_error.png",
        f"|measured - reconstruction|, RMS {decomposition.reconstruction_rms:.3g} mm", "mm", cmap="magma_r",
    ))
    return paths


def plot_explained_variance(ratio: np.ndarray, path: str | Path, count: int = 10) -> Path:
    """Fig. 8: explained variance per principal component (bars) and cumulative (line), first ``count``."""
    ratio = np.asarray(ratio, dtype=float)[:count]
    index = np.arange(1, ratio.size + 1)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.bar(index, 100 * ratio, color="tab:blue", label="per component")
    ax.plot(index, 100 * np.cumsum(ratio), "o-", color="tab:orange", label="cumulative")
    ax.set_xticks(index)
    ax.set_xlabel("principal component")
    ax.set_ylabel("explained variance (%)")
    ax.legend()
    return save_figure(fig, path)


def plot_error_boxplot(names: Sequence[str], errors: np.ndarray, path: str | Path, title: str) -> Path:
    """Fig. 9: box plot of estimation errors (M, P) mm per parameter."""
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.boxplot(np.asarray(errors, dtype=float), tick_labels=list(names), whis=(0, 100))
    ax.axhline(0.0, color="grey", linewidth=0.5)
    ax.set_ylabel("estimation error (mm)")
    ax.set_title(title)
    return save_figure(fig, path)


def plot_error_histogram(values: np.ndarray, path: str | Path, title: str, xlabel: str = "max error (mm)") -> Path:
    """Fig. 10: histogram of per-member maximum reconstruction errors (mm)."""
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(np.asarray(values, dtype=float), bins=40, color="tab:blue")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("members")
    ax.set_title(title)
    return save_figure(fig, path)


def plot_interaction_map(interactions: InteractionMap, path: str | Path, title: str, epsilon: float = 0.1) -> Path:
    """Heat map of an interaction map (core.method.interactions): one row and column per parameter and sign
    (``LOCK_L+`` = its max, ``LOCK_L-`` = its min), the peak |u(a_i + a_j) - u(a_i) - u(a_j) + u0| in mm over the
    skin in each cell (log colour scale from 1e-4 mm), cells at or above ``epsilon`` mm outlined."""
    names = interactions.names
    P = len(names)
    grid = interactions.peak_mm.transpose(0, 2, 1, 3).reshape(2 * P, 2 * P)  # (i, s_i) x (j, s_j)
    labels = [f"{n}{sign}" for n in names for sign in "+-"]
    fig, ax = plt.subplots(figsize=(1.0 + 0.62 * 2 * P, 0.6 + 0.55 * 2 * P))
    shown = np.ma.masked_invalid(np.maximum(grid, 1e-4))
    image = ax.imshow(shown, cmap="viridis", norm=matplotlib.colors.LogNorm(vmin=1e-4, vmax=max(1.0, grid[
        np.isfinite(grid)].max(initial=1.0))))
    for (r, c), value in np.ndenumerate(grid):
        if np.isfinite(value):
            ax.text(c, r, f"{value:.3f}" if value < 1 else f"{value:.2f}", ha="center", va="center", fontsize=6.5,
                    color="white" if value < 0.05 else "black")
            if value >= epsilon:
                ax.add_patch(plt.Rectangle((c - 0.5, r - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=1.2))
    ax.set_xticks(range(2 * P), labels, rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(2 * P), labels, fontsize=8)
    for k in range(1, P):
        ax.axhline(2 * k - 0.5, color="white", linewidth=1.5)
        ax.axvline(2 * k - 0.5, color="white", linewidth=1.5)
    fig.colorbar(image, ax=ax, label="max |interaction| over the skin (mm)")
    ax.set_title(f"{title}\n(red: at or above epsilon = {epsilon:g} mm; an effect only where the single effects "
                 "cannot carry it)", fontsize=9)
    return save_figure(fig, path)
