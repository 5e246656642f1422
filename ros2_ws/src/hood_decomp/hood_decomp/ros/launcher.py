"""Start the three nodes as separate processes without launch_ros (which is not on PyPI), and bring them to active.

Used by ``hood-decomp launch``, by ``hood-decomp replay --bases`` and by the tests, so the nodes always run as the
console scripts a cell would run. The nodes are lifecycle nodes: :func:`bring_up` configures and activates them
through their ``change_state`` services and says which did not come up, and why (from their /diagnostics).
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
NODE_NAMES = {"scan_node": "hood_decomp_scan", "estimator_node": "hood_decomp_estimator",
              "decomposition_node": "hood_decomp_decomposition"}
#: Budget of a bring-up, all nodes together: configure loads the bases in each node, one after the other. The three
#: nodes of the default hood took 5 s on a quiet 2-core machine, 17 s at load 5, 37 s at load 10, and 56 s / more than
#: 60 s with 16 / 24 busy processes on their one core (2026-11-25), where a 60 s budget failed the demo's bring-up.
BRING_UP_TIMEOUT_S = 120.0
#: How long a bring-up listens on /diagnostics at least, for the heartbeat of a node of the same name in another
#: process: discovery of a running participant can wait for its next announcement (Fast DDS: every 3 s), then the
#: heartbeat comes within 1 s. Measured (quiet): an existing namesake first heard 0.3, 3.4 and 3.4 s after the start.
NAMESAKE_LISTEN_S = 5.0
#: seconds after which bring-up asks a node's state again when no answer came (Participant.call's resend_s: a new
#: client's first response can be dropped by Fast DDS before it has matched the client)
GET_STATE_RESEND_S = 5.0


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


PathLike = str | os.PathLike[str]


def start_nodes(bases: PathLike, *, params_file: PathLike | Sequence[PathLike] | None = None,
                nodes: Sequence[str] = NODE_EXECUTABLES, extra_params: Sequence[str] = (),
                log_dir: pathlib.Path | None = None, activate: bool = True,
                timeout_s: float = BRING_UP_TIMEOUT_S) -> list[subprocess.Popen[bytes]]:
    """Start each node in its own process and (``activate``) bring it to active; ``extra_params`` are
    ``name:=value`` strings for every node. ``params_file``: one parameter file or several (a later one wins). The
    params files come first on the command line and ``bases`` after them, so ``bases`` wins over a file (rcl applies
    the later value). Output goes to ``log_dir/<node>.log`` when given,
    else to this process's stderr. A node that does not come up is a HoodDecompError naming it and why (all nodes
    are stopped then)."""
    from hood_decomp.ros.node_common import use_fastdds_profile  # rclpy only when nodes are started

    environment = dict(os.environ)
    use_fastdds_profile(environment)
    processes = []
    for name in nodes:
        command = [node_executable(name), "--ros-args"]
        files = [] if params_file is None else [params_file] if isinstance(params_file, str | os.PathLike) \
            else params_file
        for file in files:
            command += ["--params-file", os.fspath(file)]
        command += ["-p", f"bases:={os.fspath(bases)}"]
        for param in extra_params:
            command += ["-p", param]
        output = open(log_dir / f"{name}.log", "wb") if log_dir is not None else None  # closed by the child
        processes.append(subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT if output else None,
                                          env=environment))
    if activate:
        failures = bring_up(nodes, timeout_s, processes)
        if failures:
            stop_nodes(processes)
            raise HoodDecompError("; ".join(f"{name} did not come up: {why}" for name, why in failures.items()))
    return processes


def bring_up(nodes: Sequence[str] = NODE_EXECUTABLES, timeout_s: float = BRING_UP_TIMEOUT_S,
             processes: Sequence[subprocess.Popen[bytes]] | None = None) -> dict[str, str]:
    """Configure and activate each node (by executable name) through its lifecycle services; a node already active
    is left as it is. ``timeout_s`` is the budget of all nodes together. ``processes`` (one per node, when started
    here): a process that ended is named at once, and a node of the same name in another process on this ROS domain
    (told apart by the process id in the heartbeats) is a failure naming it: lifecycle calls reach both nodes and are
    answered by either. Returns executable -> why it is not active, for those that are not (empty: all active)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    from hood_decomp.ros.participant import Participant

    reasons: dict[str, str] = {}
    pids: dict[str, set[str]] = {}  # status name -> the process ids its heartbeats came from

    def on_diagnostics(array: DiagnosticArray) -> None:
        """A node's configure failure, from its transition report or any heartbeat after it; the heartbeats' pids."""
        for status in array.status:
            if "configure failed" in status.message:
                reasons[status.name] = status.message
            pids.setdefault(status.name, set()).update(kv.value for kv in status.values if kv.key == "pid")

    def no_answer(what: str, started: float) -> str:
        return (f"no answer to {what} within {time.monotonic() - started:.0f} s (bring-up budget {timeout_s:.0f} s "
                f"for {len(nodes)} node(s), {time.monotonic() - begin:.0f} s used)")

    failures = {}
    begin = time.monotonic()
    deadline = begin + timeout_s
    with Participant("hood_decomp_bring_up") as peer:
        peer.subscribe("/diagnostics", DiagnosticArray, on_diagnostics)
        for index, executable in enumerate(nodes):
            name = NODE_NAMES[executable]
            process = processes[index] if processes is not None else None

            def ended(process: subprocess.Popen[bytes] | None = process) -> bool:
                return process is not None and process.poll() is not None

            started = time.monotonic()
            state = peer.call(f"/{name}/get_state", GetState, GetState.Request(), deadline - time.monotonic(), ended,
                              resend_s=GET_STATE_RESEND_S)
            if state is None:
                failures[executable] = (f"exited with status {process.returncode}" if ended() else
                                        no_answer(f"/{name}/get_state", started))
                continue
            steps = {"unconfigured": (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE),
                     "inactive": (Transition.TRANSITION_ACTIVATE,), "active": ()}.get(state.current_state.label)
            if steps is None:
                failures[executable] = f"in state {state.current_state.label!r}"
                continue
            for transition in steps:
                what = "configure" if transition == Transition.TRANSITION_CONFIGURE else "activate"
                started = time.monotonic()
                response = peer.call(f"/{name}/change_state", ChangeState,
                                     ChangeState.Request(transition=Transition(id=transition)),
                                     max(1.0, deadline - time.monotonic()), ended)
                if response is None and not ended():  # its answer may be what Fast DDS dropped: ask the state
                    reached = peer.call(f"/{name}/get_state", GetState, GetState.Request(),
                                        max(1.0, deadline - time.monotonic()), ended, resend_s=GET_STATE_RESEND_S)
                    target = "inactive" if transition == Transition.TRANSITION_CONFIGURE else "active"
                    if reached is not None and reached.current_state.label == target:
                        continue
                if response is None or not response.success:
                    key = f"hood_decomp/{name}"
                    peer.wait(lambda k=key: k in reasons, 2.0)  # the reason comes on /diagnostics
                    failures[executable] = reasons.get(key, f"{what} failed" if response else no_answer(what, started))
                    break
        if processes is not None:
            # A namesake can answer before this node has started: wait for a heartbeat of each started node, and
            # listen NAMESAKE_LISTEN_S at least for a namesake's.
            started_nodes = [(executable, f"hood_decomp/{NODE_NAMES[executable]}", str(process.pid), process)
                             for executable, process in zip(nodes, processes, strict=True)]
            peer.wait(lambda: time.monotonic() - begin >= NAMESAKE_LISTEN_S and all(
                pid in pids.get(key, ()) or process.poll() is not None for _, key, pid, process in started_nodes),
                max(NAMESAKE_LISTEN_S - (time.monotonic() - begin), deadline - time.monotonic()))
            for executable, key, pid, _ in started_nodes:
                others = sorted(pids.get(key, set()) - {pid})
                if others:
                    failures[executable] = (
                        f"another process (pid {', '.join(others)}) on ROS_DOMAIN_ID "
                        f"{os.environ.get('ROS_DOMAIN_ID', '0')} also runs a node named /{NODE_NAMES[executable]}, "
                        "and lifecycle calls reach both (either answers): stop it or set ROS_DOMAIN_ID to a domain of "
                        "this cell alone" + (f"; then: {failures[executable]}" if executable in failures else ""))
    return failures


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
