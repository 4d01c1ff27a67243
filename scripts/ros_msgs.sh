#!/usr/bin/env bash
# Build the ROS 2 Jazzy message packages that PyPI's ros-jazzy wheels lack (tf2_msgs,
# foxglove_msgs) and install them into a venv that has the fleetctl [ros] extra, so that
# `from tf2_msgs.msg import TFMessage` works there. A robot with ROS from apt does not need
# this: ros-jazzy-tf2-msgs and ros-jazzy-foxglove-msgs are Debian packages.
#
#   scripts/ros_msgs.sh [VENV] [--force | --no-install --wheel-dir DIR]
#
# VENV defaults to .venv. Idempotent: a package already installed from the same inputs is
# skipped (about one interpreter start); the build cache is VENV/ros_msgs-build.
# Needs gcc, g++ and Python's headers (Debian: build-essential python3-dev); the generators
# and ROS headers come from the venv's wheels. Details: docs/client.md.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv=".venv"
if (($#)) && [[ "$1" != -* ]]; then venv="$1"; shift; fi
python="$venv/bin/python"
if [ ! -x "$python" ]; then
  echo "ros_msgs: no Python at $python (create the venv first: scripts/setup.sh)" >&2
  exit 2
fi
if ! "$python" -c "import rosidl_generator_c, rclpy" 2>/dev/null; then
  echo "ros_msgs: $venv lacks the ROS 2 wheels (pip install -e '.[ros]')" >&2
  exit 2
fi
exec "$python" "$here/ros_msgs/build.py" "$@"
