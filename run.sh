#!/usr/bin/env bash
# The two commands of the README, on a fresh Debian machine with Python 3.11:
#   ./run.sh demo [--out DIR]   set everything up, run the whole pipeline on the built-in hood, write the report
#   ./run.sh test [PYTEST ARGS] set everything up and run the test suite (what CI runs)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
command="${1:-}"
shift || true
case "$command" in
  demo)
    bash scripts/setup.sh
    exec scripts/with-env hood-decomp demo "$@"
    ;;
  test)
    bash scripts/setup.sh
    scripts/with-env ruff check .
    # The session claims a ROS domain no other test run on this machine holds, unless ROS_DOMAIN_ID is set;
    # discovery stays on loopback (tests/conftest.py, tests/ros_domain.py).
    # One worker process per core (pytest-xdist; "-n 0" in the arguments runs in this process): a test file stays on
    # one worker, so its module fixtures are built once; each worker claims its own ROS domain.
    exec scripts/with-env python -m pytest -n "${HOOD_DECOMP_TEST_WORKERS:-2}" --dist loadfile "$@"
    ;;
  *)
    echo "usage: ./run.sh demo [--out DIR] | ./run.sh test [pytest arguments]" >&2
    exit 2
    ;;
esac
