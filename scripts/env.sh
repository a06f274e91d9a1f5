# Source this file to get the tal environment: the venv plus the colcon install of ros2_ws.
# Usage: source scripts/env.sh   (after scripts/bootstrap.sh)
_tal_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck disable=SC1091
source "$_tal_root/.venv/bin/activate"
export AMENT_PREFIX_PATH="$_tal_root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$_tal_root/.venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
# colcon's setup scripts read unset variables; relax nounset while sourcing them.
case $- in *u*) _tal_nounset=1; set +u ;; *) _tal_nounset=0 ;; esac
# shellcheck disable=SC1091
source "$_tal_root/ros2_ws/install/setup.bash"
[ "$_tal_nounset" = 1 ] && set -u
export TAL_ROOT="$_tal_root"
unset _tal_root _tal_nounset
# Keep DDS discovery on this machine (loopback): nothing of tal talks to other hosts.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
