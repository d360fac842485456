#!/usr/bin/env bash
# `make bundle`: an offline installer of dran-edge for an aarch64 robot (docs/bundle.md).
#
#   tools/bundle/build_bundle.sh            (as root: it builds the C parts in an arm64 root)
#
# Environment (all optional):
#   BUNDLE_PY      the robot's Python X.Y (default 3.11 = Debian 12's; JetPack 6 is 3.10, which
#                  needs a build root with Python 3.10 and glibc <= 2.35: BUNDLE_SUITE=jammy)
#   BUNDLE_SUITE   the arm64 build root's distribution (default bookworm)
#   BUNDLE_MIRROR  its archive (default http://deb.debian.org/debian; jammy:
#                  http://ports.ubuntu.com/ubuntu-ports)
#   BUNDLE_ROOT    where the build root lives (default /var/tmp/dran-arm64/<suite>-root)
#   PYTHON         the host Python with pip (default .venv/bin/python)
#
# Output: dist/dran-edge-<version>-cpXY-aarch64/ (wheels/, libzmq.tar.gz, install.sh,
# requirements.txt, config/, systemd/, BUNDLE_INFO, SHA256SUMS) and the same as a .tar.gz.
# The C parts (draft libzmq + pyzmq, pupil-apriltags, systemd-python) are built inside the arm64
# root under qemu (tools/bundle/build_native_wheels.sh; cached in the root); everything else is
# a manylinux aarch64 wheel from PyPI (pip download --platform).
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
PYV=${BUNDLE_PY:-3.11}
SUITE=${BUNDLE_SUITE:-bookworm}
MIRROR=${BUNDLE_MIRROR:-http://deb.debian.org/debian}
ROOT=${BUNDLE_ROOT:-/var/tmp/dran-arm64/$SUITE-root}
HOSTPY=${PYTHON:-$REPO/.venv/bin/python}
TAG=cp${PYV/./}
PINS=$REPO/tools/bundle/pins-$TAG.txt
log() { echo "bundle: $*" >&2; }
die() { log "ERROR: $*"; exit 1; }

[ -f "$PINS" ] || die "no pins for Python $PYV ($PINS); write one like tools/bundle/pins-cp310.txt"
[ -x "$HOSTPY" ] || die "no host Python at $HOSTPY (make setup, or PYTHON=...)"
VERSION=$("$HOSTPY" -c 'import tomllib,sys; print(tomllib.load(open(sys.argv[1],"rb"))["project"]["version"])' "$REPO/pyproject.toml" 2>/dev/null \
          || sed -n 's/^version = "\(.*\)"/\1/p' "$REPO/pyproject.toml")
NAME=dran-edge-$VERSION-$TAG-aarch64
OUT=$REPO/dist/$NAME
t0=$SECONDS

# ------------------------------------------------------------------ C parts in the arm64 root
bash "$REPO/tools/arm64_root.sh" create "$ROOT" "$SUITE" "$MIRROR"
t_root=$((SECONDS - t0))
# libzmq (C++, the longest compile) cross-compiled here at native speed when an aarch64 cross
# compiler is installed (apt-get install g++-aarch64-linux-gnu), at the path it has in the root
BV=/var/tmp/dran-native-build/venv
if [ "$(uname -m)" != aarch64 ] && command -v aarch64-linux-gnu-g++ >/dev/null &&
   ! grep -q "patch=$(sha256sum "$REPO"/tools/patches/libzmq-udp-engine-hardening.patch | cut -c1-16)" \
       "$ROOT$BV/opt/libzmq/.dran-stamp" 2>/dev/null; then
    tx=$SECONDS
    [ -e "$BV" ] && [ ! -L "$BV/bin/python" ] && die "$BV exists on this machine and is not ours"
    mkdir -p "$BV/bin" && ln -sf "$(command -v python3)" "$BV/bin/python"
    DRAN_ZMQ_CROSS=aarch64-linux-gnu nice -n 10 bash "$REPO/tools/build_zmq_draft.sh" "$BV"
    mkdir -p "$ROOT$BV/opt" && rm -rf "$ROOT$BV/opt/libzmq" && cp -a "$BV/opt/libzmq" "$ROOT$BV/opt/"
    log "libzmq cross-compiled for aarch64 in $((SECONDS - tx)) s"
fi
rm -rf "$ROOT/build/src" && mkdir -p "$ROOT/build/src"
cp -r "$REPO/tools" "$ROOT/build/src/tools"
t1=$SECONDS
bash "$REPO/tools/arm64_root.sh" run "$ROOT" nice -n 15 bash /build/src/tools/bundle/build_native_wheels.sh \
    "/build/src/tools/bundle/pins-$TAG.txt" "/build/native-$TAG"
t_native=$((SECONDS - t1))
NATIVE=$ROOT/build/native-$TAG
ls "$NATIVE"/wheels/pyzmq-*-"$TAG"-*.whl >/dev/null 2>&1 || die "the build root's Python is not \
$PYV (built: $(ls "$NATIVE/wheels")). A bundle for Python $PYV needs a build root with that \
Python (BUNDLE_SUITE/BUNDLE_MIRROR; docs/bundle.md), or run tools/bundle/build_native_wheels.sh \
on an aarch64 machine with Python $PYV and network and copy its output to $NATIVE"

# ------------------------------------------------------------------ the bundle folder
rm -rf "$OUT" "$OUT.tar.gz" && mkdir -p "$OUT/wheels"
cp "$NATIVE"/wheels/*.whl "$NATIVE/libzmq.tar.gz" "$OUT/"
mv "$OUT"/*.whl "$OUT/wheels/"
t2=$SECONDS
PLATS=()
for p in manylinux2014_aarch64 manylinux_2_17_aarch64 manylinux_2_26_aarch64 \
         manylinux_2_27_aarch64 manylinux_2_28_aarch64; do PLATS+=(--platform "$p"); done
download() {  # pip download one pinned wheel for the robot
    "$HOSTPY" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
        --implementation cp --python-version "$PYV" "${PLATS[@]}" -d "$OUT/wheels" "$1"
}
required=()
optional_missing=()
section=pypi
while IFS= read -r line; do
    case "$line" in
        "# Built on aarch64"*) section=native ;;
        "# Optional"*) section=optional ;;
    esac
    spec=${line%%#*}; spec=${spec// /}
    [ -n "$spec" ] || continue
    case "$section" in
        pypi) download "$spec" || die "no aarch64 wheel for $spec on Python $PYV"
              required+=("$spec") ;;
        native) required+=("$spec") ;;
        optional) download "$spec" 2>/dev/null || optional_missing+=("$spec") ;;
    esac
done < "$PINS"
t_download=$((SECONDS - t2))
# dran-edge itself (pure Python)
"$HOSTPY" -m pip wheel -q --disable-pip-version-check --no-deps \
    -w "$OUT/wheels" "$REPO" >/dev/null && rm -rf "$REPO/build"
{ printf '%s\n' "# Installed by install.sh with pip --no-index (docs/bundle.md)" "${required[@]}"
  echo "dran-edge==$VERSION"; } > "$OUT/requirements.txt"
cp "$REPO/tools/bundle/install.sh" "$REPO/tools/install_drivers.py" "$OUT/"
mkdir -p "$OUT/config" "$OUT/systemd"
cp -r "$REPO/calib/tags.yaml" "$REPO/calib/cameras" "$REPO/calib/fleet" "$OUT/config/"
cp "$REPO"/systemd/*.service "$REPO/systemd/README.md" "$OUT/systemd/"
cp "$REPO/docs/bundle.md" "$OUT/README.md"
COMMIT=$(git -C "$REPO" rev-parse --short HEAD 2>/dev/null || echo unknown)
DIRTY=$(git -C "$REPO" status --porcelain 2>/dev/null | grep -q . && echo "+dirty" || true)
cat > "$OUT/BUNDLE_INFO" <<EOF
# sourced by install.sh
python=$PYV
arch=aarch64
version=$VERSION
commit=$COMMIT$DIRTY
built=$(date -u +%Y-%m-%dT%H:%M:%SZ)
build_root=$SUITE
glibc_built_against="$(cat "$NATIVE/.glibc" 2>/dev/null || echo "$SUITE's")"
drivers_without_wheel="${optional_missing[*]:-}"
EOF
(cd "$OUT" && find . -type f ! -name SHA256SUMS | sort | xargs sha256sum > SHA256SUMS)
tar -C "$REPO/dist" -czf "$OUT.tar.gz" "$NAME"
for spec in "${optional_missing[@]}"; do
    log "note: no aarch64 wheel of optional $spec for Python $PYV on PyPI: install.sh will say so"
done
log "root ${t_root} s, C parts ${t_native} s, downloads ${t_download} s, total $((SECONDS - t0)) s"
log "wrote $OUT.tar.gz ($(du -h "$OUT.tar.gz" | cut -f1)); on the robot: tar xzf $NAME.tar.gz && sudo $NAME/install.sh --robot dingo1"
