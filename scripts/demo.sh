#!/usr/bin/env bash
# The main job: set up (first run: a few minutes), replay a bundled sample bag through the five
# mosiv_ros nodes (reconstruction, lifting, identification, prediction), and write the estimates
# and a report (printed at the end) to out/demo.  Usage: bash scripts/demo.sh [BAG]
# MOSIV_PARAMS (default config/demo.yaml), MOSIV_OUT (out/demo), MOSIV_RATE (1.0) change them.
set -euo pipefail
# shellcheck source=scripts/env.sh
. "$(dirname "${BASH_SOURCE[0]}")/env.sh" || exit 1
exec python -m mosiv_ros graph "${1:-bags/elastic_on_plastic}" --rate "${MOSIV_RATE:-1.0}" \
    --params-file "${MOSIV_PARAMS:-config/demo.yaml}" --out "${MOSIV_OUT:-out/demo}"
