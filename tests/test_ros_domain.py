"""The test session's ROS domain claim (tests/ros_domain.py): two sessions on one machine never share a domain, an
explicit ROS_DOMAIN_ID is kept."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import textwrap

import pytest

from tests.ros_domain import DOMAINS, VARIABLE, claim_domain, lock_path

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _holder(directory: pathlib.Path, start: int) -> subprocess.Popen[str]:
    """Another session: a process that claims from ``start`` in ``directory``, prints its domain and holds it until
    its stdin closes."""
    code = textwrap.dedent(f"""
        import os, pathlib, sys
        from tests.ros_domain import claim_domain
        environment = {{}}
        domain, _ = claim_domain(environment, pathlib.Path({str(directory)!r}), start={start})
        print(domain, environment["{VARIABLE}"], flush=True)
        sys.stdin.read()
    """)
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, env={k: v for k, v in os.environ.items() if k != VARIABLE})


def test_sessions_starting_at_the_same_id_get_different_domains(tmp_path):
    """The old rule's collision (two pids equal mod 100): both start at the same id. Fails if the second session
    (this process, after two others) gets a domain another live session holds, or if a domain is not free again once
    its holder ended."""
    holders = [_holder(tmp_path, start=40) for _ in range(2)]
    try:
        held = [int(holder.stdout.readline().split()[0]) for holder in holders]
        assert len(set(held)) == 2 and set(held) <= set(DOMAINS), held
        environment: dict[str, str] = {}
        domain, descriptor = claim_domain(environment, tmp_path, start=40)
        assert domain not in held and environment[VARIABLE] == str(domain) and descriptor is not None
        os.close(descriptor)
    finally:
        for holder in holders:
            holder.communicate("")
    environment = {}
    again, descriptor = claim_domain(environment, tmp_path, start=40)
    os.close(descriptor)
    assert again == min(held), "the domain of an ended session stays locked"


def test_claims_wrap_around_and_stop_when_every_domain_is_held(tmp_path):
    """Fails if a claim starting at the last id does not wrap to the first, or if a machine with every domain held
    reuses one instead of saying so."""
    descriptors = []
    try:
        for expected in [*DOMAINS[-1:], *DOMAINS[:-1]]:
            domain, descriptor = claim_domain({}, tmp_path, start=len(DOMAINS) - 1)
            descriptors.append(descriptor)
            assert domain == expected
        with pytest.raises(RuntimeError, match=f"every ROS domain {DOMAINS.start}-{DOMAINS.stop - 1} is held"):
            claim_domain({}, tmp_path, start=0)
    finally:
        for descriptor in descriptors:
            os.close(descriptor)


def test_an_explicit_domain_is_kept_and_marked_held(tmp_path):
    """Fails if an explicit ROS_DOMAIN_ID is replaced, if it is not locked (so other sessions avoid it), if a held
    explicit domain is replaced, or if a value that is no domain id passes silently."""
    environment = {VARIABLE: "7"}
    domain, descriptor = claim_domain(environment, tmp_path)
    assert (domain, environment[VARIABLE]) == (7, "7") and descriptor is not None
    try:
        other, other_descriptor = claim_domain({}, tmp_path, start=6)
        os.close(other_descriptor)
        assert other == 8
        assert claim_domain({VARIABLE: "7"}, tmp_path) == (7, None)  # held: kept all the same (the user's choice)
    finally:
        os.close(descriptor)
    with pytest.raises(RuntimeError, match="ROS_DOMAIN_ID='zero': expected a domain id"):
        claim_domain({VARIABLE: "zero"}, tmp_path)


def test_a_process_started_from_a_claiming_session_claims_its_own(tmp_path):
    """The pytest-xdist workers of ``./run.sh test`` inherit the controller's environment: fails if a worker takes
    the domain its parent claimed as an explicit choice (both workers then shared it and answered each other's
    lifecycle calls), or if a user's explicit domain beside an inherited claim is not kept."""
    parent: dict[str, str] = {}
    claimed, descriptor = claim_domain(parent, tmp_path, start=40)
    worker = dict(parent)
    try:
        own, own_descriptor = claim_domain(worker, tmp_path, start=40)
        os.close(own_descriptor)
        assert own != claimed and worker[VARIABLE] == str(own), (claimed, own)
        chosen, chosen_descriptor = claim_domain({**parent, VARIABLE: "7"}, tmp_path)
        os.close(chosen_descriptor)
        assert chosen == 7  # the user's choice after a claim
    finally:
        os.close(descriptor)


def test_this_session_holds_its_domain(ros_domain):
    """Fails if the running session (tests/conftest.py) did not claim the domain its node processes inherit: another
    session starting at the same id must get a different one."""
    domain, descriptor = ros_domain
    assert os.environ[VARIABLE] == str(domain)
    if descriptor is None or domain not in DOMAINS:
        pytest.skip(f"explicit {VARIABLE}={domain}, held by another process or outside {DOMAINS}")
    holder = _holder(lock_path(domain).parent, start=DOMAINS.index(domain))
    try:
        assert int(holder.stdout.readline().split()[0]) != domain
    finally:
        holder.communicate("")
