# Source this file (bash) to use hood_decomp from the project's venv and colcon workspace:
#   source scripts/env.sh
# In an existing ROS 2 cell, source your ROS installation first and then ros2_ws/install/setup.bash instead.
_hd_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck disable=SC1091
source "$_hd_root/.venv/bin/activate"
# install/setup.bash sets PYTHONPATH, AMENT_PREFIX_PATH and LD_LIBRARY_PATH (custom message type support needs it).
# It was generated with 'set -u'-unsafe code, so relax nounset while sourcing it.
_hd_nounset=$(set +o | grep nounset); set +u
source "$_hd_root/ros2_ws/install/setup.bash"
eval "$_hd_nounset"
export PATH="$_hd_root/ros2_ws/install/hood_decomp/lib/hood_decomp:$PATH"
# The ROS wheels' bootstrapper (a .pth of the venv) re-executes every Python process once to add their libraries to
# LD_LIBRARY_PATH, a second interpreter start of 25-40 ms per command (issue 19: a one-off `hood-decomp estimate`).
# Take the path it computes once, here, and tell it so (its own guard variable).
if [ -z "${_ROS_WHEELS_BOOTSTRAP_COMPLETE:-}" ] && _hd_ld="$(python -c 'import os; print(os.environ.get("LD_LIBRARY_PATH", ""))')"; then
  export LD_LIBRARY_PATH="$_hd_ld" _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
fi
# Discovery stays on this machine unless the cell says otherwise.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# Fast DDS with a 64 MB shared-memory transport (best-effort 1M-point clouds on one host), unless the cell chose a
# profile: export FASTDDS_DEFAULT_PROFILES_FILE (even empty) before sourcing to keep yours.
[ -n "${FASTDDS_DEFAULT_PROFILES_FILE+set}" ] ||
  export FASTDDS_DEFAULT_PROFILES_FILE="$_hd_root/ros2_ws/install/hood_decomp/share/hood_decomp/config/fastdds.xml"
unset _hd_root _hd_nounset _hd_ld
