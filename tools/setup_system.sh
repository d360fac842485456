#!/usr/bin/env bash
# Installs the Debian/Ubuntu system packages dran-edge needs to build and test.
# Idempotent: packages already present are not touched; needs root (or sudo) only
# when something is missing.
set -euo pipefail

# build-essential/cmake/pkg-config: the draft-enabled libzmq and pyzmq build;
# libsystemd-dev: systemd-python; python3-venv: the project venv; libusb-1.0-0: the pyrealsense2
# wheel links it (ImportError "libusb-1.0.so.0" without it).
want=(python3-venv python3-dev build-essential cmake pkg-config libsystemd-dev dpkg-dev iproute2 libusb-1.0-0)
# ROS Noetic from Debian, only for the vins_bridge test (skipped cleanly when absent).
optional=(ros-core python3-rospy python3-nav-msgs python3-std-msgs python3-geometry-msgs
          python3-sensor-msgs)

missing=()
for p in "${want[@]}" "${optional[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null; then SUDO="sudo"; else
        echo "setup_system: missing packages ${missing[*]} and not root (no sudo): install them by hand" >&2
        exit 1
    fi
fi
echo "setup_system: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
for p in "${want[@]}"; do
    printf '%s\n' "${missing[@]}" | grep -qx "$p" && $SUDO apt-get install -y -qq --no-install-recommends "$p" >/dev/null
done
# Optional packages: a machine without them still builds and tests (the ROS test skips).
for p in "${optional[@]}"; do
    if printf '%s\n' "${missing[@]}" | grep -qx "$p"; then
        $SUDO apt-get install -y -qq --no-install-recommends "$p" >/dev/null \
            || echo "setup_system: optional package $p not installable here; its tests will skip" >&2
    fi
done
