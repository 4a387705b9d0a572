#!/usr/bin/env bash
# The tests: set up (first run: a few minutes) and run the whole test suite on the CPU.
# Extra arguments go to pytest, e.g.  bash scripts/test.sh -k bag
set -euo pipefail
# shellcheck source=scripts/env.sh
. "$(dirname "${BASH_SOURCE[0]}")/env.sh" || exit 1
exec python -m pytest "$@"
