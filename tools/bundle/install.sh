#!/usr/bin/env bash
# dran-edge offline installer for an aarch64 robot (made by `make bundle`; docs/bundle.md).
# Needs no network: every Python package comes from wheels/ next to this script.
#
#   sudo ./install.sh [--python PY] [--prefix DIR] [--etc DIR] [--robot NAME] [--no-systemd]
#
#   --python PY    the interpreter of the venv (default: python3.X of this bundle, then python3);
#                  must be the bundle's Python version (BUNDLE_INFO: python=)
#   --prefix DIR   where the venv goes: DIR/.venv (default /opt/dran-edge, as systemd/*.service)
#   --etc DIR      config directory (default /etc/dran-edge)
#   --robot NAME   install fleet/NAME.yaml of the skeleton as DIR/robot.yaml (e.g. dingo1)
#   --no-systemd   do not install the unit or create the service user (containers, chroots)
#
# Steps: venv -> required wheels (pip --no-index) -> the hardened draft libzmq into the venv ->
# check drafts + hardening stamp -> optional camera drivers (a missing one is a note) ->
# config skeleton (never overwrites) -> systemd unit -> dran-edge check-config -> what is left.
set -euo pipefail

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
# shellcheck disable=SC1091
. "$HERE/BUNDLE_INFO"          # python=3.11 version=0.1.0 arch=aarch64 ...
PREFIX=/opt/dran-edge
ETC=/etc/dran-edge
PYTHON=""
ROBOT=""
SYSTEMD=1
while [ $# -gt 0 ]; do
    case "$1" in
        --python) PYTHON=$2; shift 2 ;;
        --prefix) PREFIX=$2; shift 2 ;;
        --etc) ETC=$2; shift 2 ;;
        --robot) ROBOT=$2; shift 2 ;;
        --no-systemd) SYSTEMD=0; shift ;;
        -h|--help) sed -n '2,17p' "$0"; exit 0 ;;
        *) echo "install.sh: unknown option $1 (--help)" >&2; exit 2 ;;
    esac
done
say() { echo "install.sh: $*"; }
die() { echo "install.sh: ERROR: $*" >&2; exit 1; }
TODO=()

# ------------------------------------------------------------------ the interpreter
[ "$(uname -m)" = "$arch" ] || die "this bundle is for $arch, this machine is $(uname -m)"
pyver() { "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null; }
if [ -z "$PYTHON" ]; then
    for cand in "python$python" python3; do
        if command -v "$cand" >/dev/null && [ "$(pyver "$cand")" = "$python" ]; then
            PYTHON=$(command -v "$cand"); break
        fi
    done
    [ -n "$PYTHON" ] || die "this bundle's wheels are for Python $python; no python$python or \
python3 of that version here (python3 is $(pyver python3 || echo none)). Pass --python PATH, \
install Python $python, or build a bundle for this Python (make bundle BUNDLE_PY=X.Y; docs/bundle.md)"
fi
have=$(pyver "$PYTHON") || die "--python $PYTHON does not run"
[ "$have" = "$python" ] || die "--python $PYTHON is Python $have; this bundle is for $python"
"$PYTHON" -c 'import sys; assert sys.version_info >= (3, 10)' || die "dran-edge needs Python >= 3.10"
"$PYTHON" -c 'import venv, ensurepip' 2>/dev/null \
    || die "$PYTHON has no venv/ensurepip module (Debian/Ubuntu: apt-get install python$python-venv)"
say "Python $have ($PYTHON), $(ldd --version 2>&1 | sed -n 1p)"

# ------------------------------------------------------------------ venv + wheels, offline
VENV=$PREFIX/.venv
PY=$VENV/bin/python
mkdir -p "$PREFIX"
[ -x "$PY" ] || "$PYTHON" -m venv "$VENV"
PIP=("$PY" -m pip install -q --disable-pip-version-check --no-index --find-links "$HERE/wheels")
say "installing dran-edge $version and its pinned dependencies from wheels/ (no network)"
"${PIP[@]}" -r "$HERE/requirements.txt"
rm -rf "$VENV/opt/libzmq" && mkdir -p "$VENV/opt"
tar -C "$VENV" -xzf "$HERE/libzmq.tar.gz"
"$PY" - <<'EOF' || die "pyzmq does not load the bundle's draft libzmq (see above)"
import zmq
from dran_edge.comms.radio import hardened_libzmq_stamp
assert zmq.has("draft") and zmq.DRAFT_API, "pyzmq has no draft API"
stamp = hardened_libzmq_stamp()
assert stamp, "the loaded libzmq is not the hardened build (no .dran-stamp next to it)"
print(f"install.sh: ZeroMQ {zmq.zmq_version()} (drafts, hardened: {stamp})")
EOF

# ------------------------------------------------------------------ optional camera drivers
missing=$("$PY" "$HERE/install_drivers.py" --pip-arg=--no-index --pip-arg="--find-links=$HERE/wheels" \
          dran-edge realsense oak 2>&1 | tee /dev/stderr | sed -n "s/.*optional driver '\([a-z]*\)'.*/\1/p" | paste -sd, -)
[ -z "$missing" ] || TODO+=("camera driver(s) not installed: $missing (see the NOTE above: another Python, or camera.source: forwarded)")

# ------------------------------------------------------------------ config skeleton
mkdir -p "$ETC"
for item in tags.yaml cameras fleet; do
    if [ -e "$ETC/$item" ]; then
        say "$ETC/$item exists: left as it is"
    else
        cp -r "$HERE/config/$item" "$ETC/$item"
    fi
done
if [ -n "$ROBOT" ]; then
    [ -f "$ETC/fleet/$ROBOT.yaml" ] || die "--robot $ROBOT: no $ETC/fleet/$ROBOT.yaml"
    if [ -e "$ETC/robot.yaml" ]; then
        say "$ETC/robot.yaml exists: left as it is"
    else
        ln -s "fleet/$ROBOT.yaml" "$ETC/robot.yaml"
    fi
fi

# ------------------------------------------------------------------ systemd
if [ "$SYSTEMD" = 1 ]; then
    id dran >/dev/null 2>&1 || useradd --system --home /var/lib/dran-edge --shell /usr/sbin/nologin dran
    for g in video plugdev; do getent group "$g" >/dev/null && usermod -aG "$g" dran; done
    chgrp -R dran "$ETC" && chmod -R g+rX,o-rwx "$ETC"
    sed -e "s|/opt/dran-edge/.venv/bin/dran-edge|$VENV/bin/dran-edge|" \
        -e "s|/etc/dran-edge/robot.yaml|$ETC/robot.yaml|" \
        "$HERE/systemd/dran-edge.service" > /etc/systemd/system/dran-edge.service
    sed -e "s|/opt/dran-edge/.venv/bin/dran-edge|$VENV/bin/dran-edge|" \
        "$HERE/systemd/dran-edge@.service" > /etc/systemd/system/dran-edge@.service
    if [ -d /run/systemd/system ]; then systemctl daemon-reload; fi
    say "systemd unit installed: /etc/systemd/system/dran-edge.service"
    TODO+=("start it: systemctl enable --now dran-edge   (status: $VENV/bin/dran-edge status)")
else
    say "--no-systemd: unit not installed (systemd/ of the bundle has it)"
fi

# ------------------------------------------------------------------ check the config
key=$(sed -n 's/^ *key_file: *\([^ #]*\).*/\1/p' "$ETC/robot.yaml" 2>/dev/null | sed -n 1p)
key=${key:-$ETC/fleet.key}
# before the fleet's keys are copied in, check everything but them (they are left to do below)
NOKEYS=(); [ -f "$key" ] || NOKEYS=(--no-keys)
if [ -e "$ETC/robot.yaml" ]; then
    "$VENV/bin/dran-edge" check-config "${NOKEYS[@]}" "$ETC/robot.yaml" \
        || die "$ETC/robot.yaml does not load (above)"
else
    for f in "$ETC"/fleet/*.yaml; do "$VENV/bin/dran-edge" check-config --no-keys "$f" >/dev/null \
        || die "$f does not load"; done
    say "skeleton configs load ($ETC/fleet/*.yaml)"
    TODO+=("choose this robot's config: ln -s fleet/<robot>.yaml $ETC/robot.yaml (or install.sh --robot <robot>); edit its neighbours' addresses")
fi
[ -f "$key" ] || TODO+=("fleet key: on ONE machine '$VENV/bin/dran-edge fleet-key new fleet.key', then on every robot: install -m 0600 -o dran -g dran fleet.key $key")
TODO+=("calibration: measure this robot's camera and the tag map into $ETC/cameras/<robot>/ and $ETC/tags.yaml (docs/calibration.md); the skeleton holds the example fleet's values")

say "installed: $VENV (dran-edge $("$VENV/bin/dran-edge" --version 2>/dev/null | tail -n1))"
echo
echo "Left to do:"
for t in "${TODO[@]}"; do echo "  - $t"; done
