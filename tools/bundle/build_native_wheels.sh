#!/usr/bin/env bash
# The offline bundle's C parts, built on the target architecture (inside the arm64 root under
# qemu, or natively on an aarch64 machine with network):
#
#   tools/bundle/build_native_wheels.sh PINS OUT
#
# - the draft-enabled, hardened libzmq (tools/build_zmq_draft.sh: the distribution's zeromq3
#   source + tools/patches) -> OUT/libzmq.tar.gz (opt/libzmq/, with its .dran-stamp)
# - pyzmq from source against it -> OUT/wheels/pyzmq-*.whl whose extension finds libzmq through
#   a relative RUNPATH ($ORIGIN/../../../../../../opt/libzmq/lib: <venv>/opt/libzmq/lib,
#   where install.sh unpacks libzmq.tar.gz), so the venv can live anywhere;
# - pupil-apriltags (no aarch64 wheel on PyPI) and systemd-python (sdist only) -> OUT/wheels/.
# Versions come from PINS (tools/bundle/pins-cpXY.txt). The wheels are for this machine's
# python3 (its version must be the bundle's) and glibc (the robot's must be at least as new).
# Skips everything when OUT already holds them for the same pins and patch (OUT/.stamp).
set -euo pipefail

PINS=$(readlink -f "$1")
OUT=$(mkdir -p "$2" && cd "$2" && pwd)
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)   # tools/
log() { echo "build_native_wheels: $*" >&2; }
die() { log "ERROR: $*"; exit 1; }

pin() { sed -n "s/^$1==\([^ ;#]*\).*/\1/p" "$PINS" | sed -n 1p; }
STAMP_TEXT="pins=$(sha256sum "$PINS" | cut -c1-16) patch=$(sha256sum "$HERE/patches/"*.patch | sha256sum | cut -c1-16) build=$(sha256sum "$0" "$HERE/build_zmq_draft.sh" | sha256sum | cut -c1-16)"
if [ -f "$OUT/.stamp" ] && [ "$(cat "$OUT/.stamp")" = "$STAMP_TEXT" ]; then
    log "up to date ($STAMP_TEXT)"
    exit 0
fi

t0=$SECONDS
if ! dpkg-query -W -f='${Status}' build-essential 2>/dev/null | grep -q "install ok installed" ||
   ! command -v patchelf >/dev/null; then
    log "apt-get install the build tools"
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends ca-certificates python3 python3-venv \
        python3-dev build-essential cmake pkg-config dpkg-dev libsystemd-dev patchelf \
        >/dev/null
fi
log "apt: $((SECONDS - t0)) s"

BUILD=/var/tmp/dran-native-build
VENV=$BUILD/venv
mkdir -p "$BUILD"
[ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
"$VENV/bin/python" -m pip install -q -U pip setuptools wheel
PYV=$("$VENV/bin/python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
ldd --version 2>&1 | sed -n 1p > "$OUT/.glibc"
log "python $PYV, $(cat "$OUT/.glibc")"

t1=$SECONDS
# libzmq cross-compiled on the host (build_bundle.sh) when its stamp says so: build only pyzmq
if grep -q "cross=" "$VENV/opt/libzmq/.dran-stamp" 2>/dev/null; then export DRAN_ZMQ_PREBUILT=1; fi
DRAN_PYZMQ_SPEC="pyzmq==$(pin pyzmq)" bash "$HERE/build_zmq_draft.sh" "$VENV"
log "libzmq + pyzmq: $((SECONDS - t1)) s"

rm -rf "$OUT/wheels" && mkdir -p "$OUT/wheels"
# pyzmq: the same build, its RUNPATH made relative to the venv
WHL=$(ls "$VENV"/opt/zmq-build/wheels/pyzmq-*.whl)
UNPACK=$BUILD/pyzmq-unpack
rm -rf "$UNPACK" && mkdir -p "$UNPACK"
"$VENV/bin/python" -m wheel unpack -d "$UNPACK" "$WHL" >/dev/null
for so in $(find "$UNPACK" -name '_zmq*.so'); do
    rel=$(dirname "${so#"$UNPACK"/*/}")            # zmq/backend/cython
    up=$(echo "$rel" | awk -F/ '{for (i = 0; i < NF + 3; i++) printf "../"}')  # + site-packages, pythonX.Y, lib
    patchelf --set-rpath "\$ORIGIN/${up}opt/libzmq/lib" "$so"
    log "pyzmq RUNPATH: $(patchelf --print-rpath "$so")"
done
"$VENV/bin/python" -m wheel pack -d "$OUT/wheels" "$UNPACK"/pyzmq-* >/dev/null

tar -C "$VENV" -czf "$OUT/libzmq.tar.gz" opt/libzmq
t2=$SECONDS
"$VENV/bin/python" -m pip wheel -q --no-deps --no-binary pupil-apriltags,systemd-python \
    -w "$OUT/wheels" "pupil-apriltags==$(pin pupil-apriltags)" "systemd-python==$(pin systemd-python)"
log "pupil-apriltags + systemd-python: $((SECONDS - t2)) s"
ls "$OUT/wheels" >&2
echo "$STAMP_TEXT" > "$OUT/.stamp"
log "done in $((SECONDS - t0)) s"
