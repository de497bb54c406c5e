#!/usr/bin/env bash
# Make sure ROS 1's own rosbag (Debian's python3-rosbag, with roslz4) and sensor_msgs are
# importable by the system python: the interop tests read our ROS 1 bags with them and write
# bags with them for our reader (tests/sensorbox/test_ros1_interop.py). They skip without them.
# Usage: ensure_ros1.sh
set -u
sys_py=/usr/bin/python3
pkgs="python3-rosbag python3-sensor-msgs"
if [ -x "$sys_py" ] && "$sys_py" -c 'import rosbag, roslz4, sensor_msgs.msg' >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "Installing $pkgs (ROS 1 interop tests) with apt-get..."
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq && apt-get install -y -qq $pkgs >/dev/null || {
    echo "error: apt-get install $pkgs failed" >&2; exit 1; }
  "$sys_py" -c 'import rosbag, roslz4, sensor_msgs.msg' || exit 1
else
  echo "note: the ROS 1 interop tests will be skipped. To run them: sudo apt-get install -y $pkgs"
fi
