"""The main job, ``hood-decomp demo``: the whole pipeline on the built-in hood (``run``, its ``steps`` over one
shared state and ``config``), ending in a report (``report`` builds it, ``html`` writes it, ``figures`` draws its
pictures that are not the method's own).

May import: everything below it (``core``, ``io``, ``ros``, ``plots``, ``synthetic``); nothing imports it but ``cli``.
"""

from hood_decomp.demo.config import DemoConfig
from hood_decomp.demo.run import run_demo

__all__ = ["DemoConfig", "run_demo"]
