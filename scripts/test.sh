#!/usr/bin/env bash
# The tests: set up (first run: a few minutes) and run the whole test suite on the CPU, in
# MOSIV_TEST_WORKERS (2) pytest-xdist processes. Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -m "not slow"    the fast tier (no fits, recordings or node processes)
#   bash scripts/test.sh -k bag -n 0      some tests, in this process
set -euo pipefail
# shellcheck source=scripts/env.sh
. "$(dirname "${BASH_SOURCE[0]}")/env.sh" || exit 1
exec python -m pytest -n "${MOSIV_TEST_WORKERS:-2}" "$@"
