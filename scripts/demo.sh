#!/usr/bin/env bash
# The main job: set up (first run: a few minutes) and replay a bundled sample bag through the
# mosiv_ros node graph, printing what each node receives.  Usage: bash scripts/demo.sh [BAG]
set -euo pipefail
# shellcheck source=scripts/env.sh
. "$(dirname "${BASH_SOURCE[0]}")/env.sh" || exit 1
exec python -m mosiv_ros graph "${1:-bags/shapes_demo}" --rate "${MOSIV_RATE:-1.0}"
