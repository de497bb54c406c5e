#!/usr/bin/env bash
# Make sure Open3D can load its system dependency libusb-1.0.
# Usage: ensure_libusb.sh PYTHON
set -u
py=${1:-python3}
if "$py" -c 'import open3d' >/dev/null 2>&1; then
  exit 0
fi
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "warning: open3d does not import, but libusb-1.0 is present:" >&2
  "$py" -c 'import open3d' >&2
  exit 1
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "Installing libusb-1.0-0 (needed by Open3D) with apt-get..."
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null || {
    echo "error: apt-get install libusb-1.0-0 failed" >&2; exit 1; }
  "$py" -c 'import open3d' || exit 1
else
  echo "error: Open3D needs libusb-1.0. Run: sudo apt-get install -y libusb-1.0-0" >&2
  exit 1
fi
