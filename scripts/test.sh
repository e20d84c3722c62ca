#!/usr/bin/env bash
# Set up (scripts/setup.sh, fast when done) and run the test suite:
#   bash scripts/test.sh [pytest args...]
# Extra arguments go to pytest; the test/ folder is run unless a path is given.
# Each run gets a private ROS 2 graph: ROS_DOMAIN_ID random in 1..101 (unless set)
# and discovery limited to this machine.
# The tests run in parallel, one pytest-xdist worker per core (REDMAX_TEST_WORKERS overrides; 1 runs them in
# one process), whole files to a worker (--dist loadfile: a file's module fixtures, e.g. rclpy.init, stay in
# one process); test/conftest.py gives each worker a ROS domain of its own. Passing -n yourself wins.
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

workers="${REDMAX_TEST_WORKERS:-$(nproc 2>/dev/null || echo 1)}"
parallel=()
if [ "$workers" -gt 1 ] && python -c "import xdist" 2>/dev/null; then
  parallel=(-n "$workers" --dist loadfile)
fi
for arg in "$@"; do
  case "$arg" in -n|-n*|--numprocesses*|no:xdist) parallel=() ;; esac
done

echo "[test] ROS_DOMAIN_ID=$ROS_DOMAIN_ID python -m pytest -q --durations=20 ${parallel[*]} ${targets[*]} $*"
status=0
python -m pytest -q --durations=20 ${parallel[@]+"${parallel[@]}"} "${targets[@]}" "$@" || status=$?
if [ "$status" -eq 5 ]; then
  echo "[test] error: pytest collected no tests (exit 5)" >&2
fi
exit "$status"
