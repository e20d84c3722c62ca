#!/usr/bin/env bash
# Set up (scripts/setup.sh, fast when done) and run the test suite:
#   bash scripts/test.sh [pytest args...]
# Extra arguments go to pytest; the test/ folder is run unless a path is given.
# Each run gets a private ROS 2 graph: ROS_DOMAIN_ID random in 1..101 (unless set)
# and discovery limited to this machine.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

bash scripts/setup.sh
# shellcheck source=env.sh
source scripts/env.sh

export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( RANDOM % 101 + 1 ))}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_LOG_DIR="${ROS_LOG_DIR:-$ROOT/log/ros}"

targets=(test)
for arg in "$@"; do
  case "$arg" in -*) continue ;; esac
  if [ -e "${arg%%::*}" ]; then targets=(); break; fi
done

echo "[test] ROS_DOMAIN_ID=$ROS_DOMAIN_ID python -m pytest -q ${targets[*]} $*"
status=0
python -m pytest -q "${targets[@]}" "$@" || status=$?
if [ "$status" -eq 5 ]; then
  echo "[test] error: pytest collected no tests (exit 5)" >&2
fi
exit "$status"
