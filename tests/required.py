"""Required parts of the test suite: the colcon build (ROS layer), CalculiX, CloudCompare and the browser.

A local run may lack one of them and skips its tests with the reason shown. CI must not: with ``CI`` set to a true
value (what CI runners set) or ``HOOD_DECOMP_REQUIRE_ALL=1``, a missing part fails the run and names what is missing,
so a green CI never hides a whole layer that was not tested.
"""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
from types import ModuleType

import pytest

PARTS = ("colcon build", "CalculiX", "CloudCompare", "browser")


def required_mode() -> bool:
    """True when a missing part must fail the run (CI, or HOOD_DECOMP_REQUIRE_ALL=1)."""
    def truthy(name: str) -> bool:
        return os.environ.get(name, "").strip().lower() not in ("", "0", "false", "no")

    return truthy("CI") or truthy("HOOD_DECOMP_REQUIRE_ALL")


def missing(part: str, reason: str) -> None:
    """Skip (a local run) or fail (CI) because ``part`` is not there; ``reason`` says why and how to get it."""
    if part not in PARTS:
        raise ValueError(f"unknown required part {part!r}, expected one of {PARTS}")
    message = f"required part missing: {part}: {reason}"
    if required_mode():
        pytest.fail(message + " (CI or HOOD_DECOMP_REQUIRE_ALL is set, so this fails instead of skipping)",
                    pytrace=False)
    pytest.skip(message, allow_module_level=True)


def require_import(module: str, part: str, reason: str) -> ModuleType:
    """The imported module, or :func:`missing` when it cannot be imported (at module level: the whole file)."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        missing(part, f"{reason} ({error})")
        raise  # not reached: missing() always raises


def ensure_ccx() -> None:
    """CalculiX's ``ccx`` on PATH: installed with apt-get when root, else :func:`missing`."""
    if shutil.which("ccx"):
        return
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        missing("CalculiX", "ccx (Debian calculix-ccx) is not installed and we are not root to apt-get it")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for command in (["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", "calculix-ccx"]):
        subprocess.run(command, check=False, capture_output=True, env=env, timeout=600)
    if not shutil.which("ccx"):
        missing("CalculiX", "apt-get install calculix-ccx did not provide ccx")
