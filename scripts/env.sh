# Source me (bash): `source scripts/env.sh` after scripts/setup.sh has run.
# Puts the project venv (.venv: ROS 2 Jazzy wheels + redmax_ros editable) and the
# colcon-built interface packages (install_msgs/: redmax_msgs) on the paths, so
# rclpy, the standard messages and redmax_msgs import and the console scripts
# (redmax_run, redmax_node, redmax_bench) are on PATH. Safe to source twice.
_redmax_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

# prepend DIR to the :-separated variable NAME, once
_redmax_prepend() {
  local name="$1" dir="$2" cur
  cur="${!name:-}"
  case ":$cur:" in *":$dir:"*) return 0 ;; esac
  export "$name=$dir${cur:+:$cur}"
}

if [ ! -x "$_redmax_root/.venv/bin/python" ]; then
  echo "scripts/env.sh: $_redmax_root/.venv is missing; run scripts/setup.sh first" >&2
else
  export VIRTUAL_ENV="$_redmax_root/.venv"
  _redmax_prepend PATH "$VIRTUAL_ENV/bin"
  # The venv prefix is an ament prefix (share/<pkg>, share/ament_index).
  _redmax_prepend AMENT_PREFIX_PATH "$VIRTUAL_ENV"
  _redmax_prepend CMAKE_PREFIX_PATH "$VIRTUAL_ENV"
  # install_msgs/ is a colcon --merge-install prefix made by scripts/setup.sh.
  _redmax_msgs="$_redmax_root/install_msgs"
  if [ -d "$_redmax_msgs" ]; then
    _redmax_prepend AMENT_PREFIX_PATH "$_redmax_msgs"
    _redmax_prepend CMAKE_PREFIX_PATH "$_redmax_msgs"
    _redmax_prepend LD_LIBRARY_PATH "$_redmax_msgs/lib"
    for _redmax_sp in "$_redmax_msgs"/lib/python3*/site-packages; do
      [ -d "$_redmax_sp" ] && _redmax_prepend PYTHONPATH "$_redmax_sp"
    done
    unset _redmax_sp
  fi
  unset _redmax_msgs
  # The only RMW the wheels provide.
  export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
fi
unset _redmax_root
unset -f _redmax_prepend
