#!/usr/bin/env bash
# Set up a development machine: Debian packages the tests use, and a virtualenv in .venv
# with fleetctl installed editable with every extra. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

# g++ and python3-dev: scripts/ros_msgs.sh compiles tf2_msgs/foxglove_msgs for the venv.
# faketime: tests/client/ros/test_executor.py steps a client's wall clock back.
APT_PACKAGES=(chromium wireguard-go wireguard-tools iproute2 debootstrap libjs-three libjs-leaflet
              g++ python3-dev faketime)
missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
  echo "setup: installing Debian packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

PYTHON="${PYTHON:-python3}"
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q -e '.[ros,dev]'
# tf2_msgs and foxglove_msgs have no PyPI wheel: build them into the venv (docs/client.md).
scripts/ros_msgs.sh .venv
