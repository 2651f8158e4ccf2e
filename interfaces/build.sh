#!/usr/bin/env bash
# Builds the message packages in interfaces/ (tf2_msgs) into a virtual environment that has ROS 2
# Jazzy from PyPI, with the rosidl generators from PyPI. Skipped for a package that already imports
# (a ROS install, or an earlier build).   Usage: interfaces/build.sh VENV
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
VENV="$(cd "${1:?usage: interfaces/build.sh VENV}" && pwd)"
PYBIN="$VENV/bin/python"
say() { echo "ar-tracking.sh: $*" >&2; }

missing_tools() {
  local m=()
  command -v cmake >/dev/null 2>&1 || m+=(cmake)
  command -v c++ >/dev/null 2>&1 || m+=(g++)
  command -v make >/dev/null 2>&1 || command -v ninja >/dev/null 2>&1 || m+=(make)
  "$PYBIN" -c 'import os, sysconfig, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
    || m+=(python3-dev)
  echo "${m[@]:-}"
}

for pkg_dir in "$HERE"/*/; do
  pkg="$(basename "$pkg_dir")"
  [ -f "$pkg_dir/package.xml" ] || continue
  if "$PYBIN" -c "import $pkg.msg" >/dev/null 2>&1; then continue; fi
  start=$(date +%s)
  say "building the $pkg messages (rosidl generators from PyPI, about half a minute) ..."
  tools="$(missing_tools)"
  if [ -n "$tools" ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
      say "  installing $tools (apt)"
      apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $tools >/dev/null
    else
      say "cannot build $pkg: install $tools (or source a ROS 2 Jazzy install, which has $pkg)"; exit 1
    fi
  fi
  say "  [1/3] build tools (pip)"
  "$PYBIN" -m pip install -q --disable-pip-version-check -r "$HERE/requirements.txt"
  build="$VENV/.build/$pkg"; rm -rf "$build"; mkdir -p "$build"
  gen=(); command -v ninja >/dev/null 2>&1 && gen=(-G Ninja)
  export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH"
  say "  [2/3] cmake configure"
  if ! cmake -S "$pkg_dir" -B "$build" "${gen[@]}" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
      -DPython3_EXECUTABLE="$PYBIN" -DCMAKE_INSTALL_PREFIX="$VENV" >"$build/configure.log" 2>&1; then
    say "cmake configure of $pkg failed; see $build/configure.log"; exit 1
  fi
  say "  [3/3] compile and install into $VENV"
  if ! cmake --build "$build" --parallel 2 >"$build/build.log" 2>&1 \
      || ! cmake --install "$build" >"$build/install.log" 2>&1; then
    say "building $pkg failed; see $build/build.log"; exit 1
  fi
  if ! "$PYBIN" -c "import $pkg.msg" >/dev/null 2>&1; then
    say "$pkg was built but does not import"; exit 1
  fi
  say "  $pkg ready ($(( $(date +%s) - start )) s)"
done
