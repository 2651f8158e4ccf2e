#!/usr/bin/env bash
# Installs what is missing (a virtual environment with ROS 2 Jazzy from PyPI and the package),
# then runs:  ./ar-tracking.sh demo | test | <any ar-tracking arguments>
set -euo pipefail
cd "$(dirname "$0")"
VENV="${AR_TRACKING_VENV:-.venv}"
PY="${PYTHON:-python3}"

if ! command -v "$PY" >/dev/null 2>&1; then
  echo "ar-tracking.sh: $PY not found; install Python 3.10 or newer" >&2; exit 1
fi
if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then
  echo "ar-tracking.sh: Python 3.10 or newer is needed ($("$PY" --version 2>&1))" >&2; exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
  if ! "$PY" -m venv "$VENV" >/dev/null 2>&1; then
    # Debian/Ubuntu ship venv separately.
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
      apt-get update -qq && apt-get install -y -qq python3-venv >/dev/null
      rm -rf "$VENV"; "$PY" -m venv "$VENV"
    else
      echo "ar-tracking.sh: cannot create a virtual environment; install python3-venv" >&2; exit 1
    fi
  fi
fi
# Reinstall when the package's dependencies change.
STAMP="$VENV/.ar_tracking-$(cat setup.py | "$VENV/bin/python" -c 'import hashlib,sys; print(hashlib.sha1(sys.stdin.buffer.read()).hexdigest()[:12])')"
if [ ! -f "$STAMP" ]; then
  echo "ar-tracking.sh: installing ar_tracking and ROS 2 Jazzy (PyPI) into $VENV ..." >&2
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check -e '.[ros,test,bench]'
  rm -f "$VENV"/.ar_tracking-*; touch "$STAMP"
fi
# Message packages that no wheel ships (tf2_msgs, for /tf): built once from interfaces/ with the
# rosidl generators from PyPI; skipped where they already import (e.g. a ROS install).
ISTAMP="$VENV/.interfaces-$(cat interfaces/*/package.xml interfaces/*/CMakeLists.txt interfaces/*/msg/*.msg | "$VENV/bin/python" -c 'import hashlib,sys; print(hashlib.sha1(sys.stdin.buffer.read()).hexdigest()[:12])')"
if [ ! -f "$ISTAMP" ]; then
  if interfaces/build.sh "$VENV"; then
    rm -f "$VENV"/.interfaces-*; touch "$ISTAMP"
  else
    # Everything but TF works without it: go on, and try again next time.
    echo "ar-tracking.sh: continuing without tf2_msgs (the nodes publish no /tf)" >&2
  fi
fi

cmd="${1:-demo}"; [ $# -gt 0 ] && shift
# PostgreSQL + PostGIS for the shared-store tests (a throwaway cluster per test session): installed
# from Debian when running the tests as root with apt; otherwise those tests skip and say why.
if [ "$cmd" = test ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 \
   && ! { compgen -G '/usr/lib/postgresql/*/bin/initdb' && compgen -G '/usr/share/postgresql/*/extension/postgis.control'; } >/dev/null; then
  echo "ar-tracking.sh: installing PostgreSQL and PostGIS (apt) for the store tests ..." >&2
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql postgis; } >/dev/null 2>&1 \
    || echo "ar-tracking.sh: PostgreSQL/PostGIS not installed; the PostGIS store tests will skip" >&2
fi
case "$cmd" in
  # Two workers (pytest-xdist): the suite is half waiting (replays at bag speed, discovery), so
  # two processes on two cores take ~4 instead of ~7 minutes. AR_TRACKING_TEST_WORKERS=0: serial.
  test) exec "$VENV/bin/python" -m pytest -n "${AR_TRACKING_TEST_WORKERS:-2}" "$@" ;;
  *)    exec "$VENV/bin/ar-tracking" "$cmd" "$@" ;;
esac
