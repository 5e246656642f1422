"""hood_decomp: decompose scanned deviations of sheet-metal assemblies into boundary effects.

Layers (imports point one way, downwards):
- ``hood_decomp.core``: numerical core (numpy/scipy only; no rclpy, no message types). Millimetres, newtons.
- ``hood_decomp.io``: model/mesh files, ensemble store, saved bases, bags.
- ``hood_decomp.ros``: message <-> array adapters (mm <-> m happens here only) and the three thin nodes.
- ``hood_decomp.cli``: the ``hood-decomp`` command line.
"""

__version__ = "0.1.0"
