"""Pictures of results: skin fields, contribution plots and the estimators' accuracy (``method``), residual maps and
the before/after of closing the loop (``close_loop``), each saved by ``figure.save_figure``. Uses matplotlib's Agg
backend; nothing is shown on screen.

May import: ``hood_decomp.core`` and ``hood_decomp.errors``.
"""

from hood_decomp.plots.close_loop import plot_before_after, plot_residual_maps
from hood_decomp.plots.figure import save_figure
from hood_decomp.plots.method import plot_contributions, plot_interaction_map, plot_skin_field

__all__ = ["plot_before_after", "plot_contributions", "plot_interaction_map", "plot_residual_maps", "plot_skin_field",
           "save_figure"]
