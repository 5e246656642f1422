"""A ROS domain of its own for each test session on this machine.

Two test runs (or a test run and a hood_decomp demo) on one ROS_DOMAIN_ID see each other's nodes: they have the same
names, so a lifecycle call of one run is answered by the other's node (get_state "active" before this run's node
has even started; its configure request reaching the other's node). ``1 + pid % 100`` gave two concurrent runs the
same domain once in 100 pairs. A session therefore claims a domain with an exclusive ``flock`` on a lock file per
domain in ``/tmp`` (fixed, not the session's temp directory: two sessions with other TMPDIRs took the same domain),
held until the process ends (the kernel releases it even on SIGKILL). Only test sessions take these locks: a demo or
``hood-decomp launch`` on the same explicit domain is not kept out (its bring-up names a namesake node instead).
A claim is marked in the environment (:data:`CLAIMED`), so that processes started from a claiming session (the
pytest-xdist workers of ``./run.sh test``) claim domains of their own instead of taking the inherited one as a user's
explicit choice: two workers on one domain answer each other's lifecycle calls.
"""

from __future__ import annotations

import fcntl
import os
import pathlib
from collections.abc import MutableMapping

#: Domains a claim may take. 0 is ROS's default (what a user's shell uses); on Linux, ids up to 101 keep the DDS
#: ports out of the kernel's ephemeral port range.
DOMAINS = range(1, 102)
VARIABLE = "ROS_DOMAIN_ID"
#: Set beside VARIABLE by a claim: a ROS_DOMAIN_ID equal to it was inherited from a claiming session, not chosen
CLAIMED = "HOOD_DECOMP_CLAIMED_ROS_DOMAIN_ID"
#: Where the locks live: one directory for every process on the machine, whatever its TMPDIR.
LOCK_DIRECTORY = pathlib.Path("/tmp")


def lock_path(domain: int, directory: pathlib.Path | None = None) -> pathlib.Path:
    return (directory or LOCK_DIRECTORY) / f"hood_decomp_ros_domain_{domain}.lock"


def try_lock(domain: int, directory: pathlib.Path | None = None) -> int | None:
    """An open descriptor holding the exclusive lock of ``domain``, or None when another process holds it (or its
    lock file belongs to another user and cannot be opened: taken as held)."""
    path = lock_path(domain, directory)
    try:
        # Read-only, created only when missing: another user's file in sticky /tmp cannot be opened with O_CREAT.
        try:
            descriptor = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            descriptor = os.open(path, os.O_RDONLY | os.O_CREAT, 0o644)
    except PermissionError:
        return None
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(descriptor)
        return None
    return descriptor


def claim_domain(environment: MutableMapping[str, str] = os.environ, directory: pathlib.Path | None = None,
                 start: int | None = None) -> tuple[int, int | None]:
    """Claim a ROS domain for this process and set ``environment[ROS_DOMAIN_ID]`` to it (child processes inherit it).

    An explicit ``ROS_DOMAIN_ID`` in ``environment`` is kept (its lock is taken too when free, so other sessions
    avoid it); one a claiming session set (equal to ``environment[CLAIMED]``: this process was started from it) is
    not explicit. Otherwise the ids of :data:`DOMAINS` are tried in order from ``start`` (default: derived from the pid,
    so concurrent sessions rarely try the same ids first) and the first whose lock is free is taken. Returns the
    domain and the descriptor holding its lock (None: an explicit domain another process holds); the lock lasts while
    the descriptor stays open. Raises RuntimeError when every domain is held."""
    explicit = environment.get(VARIABLE, "").strip()
    if explicit and explicit != environment.get(CLAIMED):
        if not explicit.isdigit():
            raise RuntimeError(f"{VARIABLE}={explicit!r}: expected a domain id (an integer, e.g. 1-101)")
        return int(explicit), try_lock(int(explicit), directory)
    first = os.getpid() if start is None else start
    for offset in range(len(DOMAINS)):
        domain = DOMAINS[(first + offset) % len(DOMAINS)]
        descriptor = try_lock(domain, directory)
        if descriptor is not None:
            environment[VARIABLE] = environment[CLAIMED] = str(domain)
            return domain, descriptor
    raise RuntimeError(f"every ROS domain {DOMAINS.start}-{DOMAINS.stop - 1} is held by another hood_decomp test "
                       f"session (lock files {lock_path(DOMAINS.start, directory)} ...): set {VARIABLE} to choose one")
