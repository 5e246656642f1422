"""``hood-decomp shift``: a shift of parts processed on Dask into a results history, with statistical process
control, recurring residuals turned into measured effects, and a report. An application package like ``demo``:
``sources`` (bags and files to part tasks), ``part`` (one part through the nodes' core path), ``runner`` (the Dask
batch into the history), ``spc`` (control charts, run rules, capability), ``report`` (HTML and figures).

May import: everything of the package below the applications (core, io, synthetic, plots, ros), and the demo's HTML
page builder (``hood_decomp.demo.html``).
"""
