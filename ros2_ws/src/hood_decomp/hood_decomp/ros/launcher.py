"""Start the three nodes as separate processes without launch_ros (which is not on PyPI).

Used by ``hood-decomp launch``, by ``hood-decomp replay --bases`` and by the tests, so the nodes always run as the
console scripts a cell would run.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence

from hood_decomp.errors import HoodDecompError

NODE_EXECUTABLES: tuple[str, ...] = ("scan_node", "estimator_node", "decomposition_node")


def node_executable(name: str) -> str:
    """Path of a node's console script in the colcon install space (lib/hood_decomp/), or on PATH."""
    try:
        from ament_index_python.packages import get_package_prefix

        candidate = pathlib.Path(get_package_prefix("hood_decomp")) / "lib" / "hood_decomp" / name
        if candidate.is_file():
            return str(candidate)
    except (ImportError, LookupError, ValueError):
        pass
    found = shutil.which(name)
    if found is None:
        raise HoodDecompError(f"node executable {name!r} not found: source scripts/env.sh (or install/setup.bash)")
    return found


def start_nodes(bases: str | os.PathLike[str], *, params_file: str | os.PathLike[str] | None = None,
                nodes: Sequence[str] = NODE_EXECUTABLES, extra_params: Sequence[str] = (),
                log_dir: pathlib.Path | None = None) -> list[subprocess.Popen[bytes]]:
    """Start each node in its own process; ``extra_params`` are ``name:=value`` strings for every node.
    Output goes to ``log_dir/<node>.log`` when given, else to this process's stderr."""
    processes = []
    for name in nodes:
        command = [node_executable(name), "--ros-args", "-p", f"bases:={os.fspath(bases)}"]
        if params_file is not None:
            command += ["--params-file", os.fspath(params_file)]
        for param in extra_params:
            command += ["-p", param]
        output = open(log_dir / f"{name}.log", "wb") if log_dir is not None else None  # closed by the child
        processes.append(subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT if output else None))
    return processes


def stop_nodes(processes: Sequence[subprocess.Popen[bytes]], timeout: float = 10.0) -> list[int]:
    """SIGINT each node (rclpy shuts down cleanly), then kill what is left after ``timeout`` s; exit codes."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    deadline = time.monotonic() + timeout
    codes = []
    for process in processes:
        try:
            codes.append(process.wait(max(0.1, deadline - time.monotonic())))
        except subprocess.TimeoutExpired:
            process.kill()
            codes.append(process.wait())
    return codes


def run_until_interrupted(processes: Sequence[subprocess.Popen[bytes]]) -> int:
    """Wait while the nodes run; Ctrl-C or SIGTERM stops all of them. Non-zero if a node died on its own."""
    stop = False

    def request_stop(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, request_stop)
    try:
        while not stop and all(process.poll() is None for process in processes):
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    died = [(p.args[0], p.returncode) for p in processes if p.returncode is not None]
    stop_nodes(processes)
    for executable, code in died:
        print(f"hood-decomp launch: {pathlib.Path(executable).name} exited with status {code}", file=sys.stderr)
    return 1 if died else 0
