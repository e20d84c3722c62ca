#!/usr/bin/env bash
# Set up (scripts/setup.sh, fast when done) and run the main job on the default
# scene. Extra arguments are appended to the command.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

bash scripts/setup.sh
# shellcheck source=env.sh
source scripts/env.sh
mkdir -p runs

# ---- MAIN JOB: the one command this script runs (change it here) ----
redmax_node --ros-args --params-file config/hand.yaml "$@"   # the hand, free-run at 1x, MCAP logs in logs/; Ctrl-C to stop
