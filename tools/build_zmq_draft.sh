#!/usr/bin/env bash
# Build libzmq with the DRAFT API (UDP RADIO/DISH) plus our UDP-engine hardening patch,
# install it into VENV/opt/libzmq, and install pyzmq from source against it.
#
#   tools/build_zmq_draft.sh [VENV]          (default VENV: .venv)
#
# Why: no Debian/Ubuntu libzmq package and no pyzmq wheel has the draft API, and every
# libzmq release up to 4.3.5 can be aborted by one malformed UDP datagram
# (tools/patches/libzmq-udp-engine-hardening.patch explains the bugs and the fix).
#
# Source: the distribution's own `zeromq3` source package, fetched with `apt-get source`
# through a private apt configuration under the cache folder whose deb-src entries are
# derived from the machine's configured Debian/Ubuntu mirrors. Nothing in /etc is changed
# and no root is needed. Only the package registries (apt mirror, PyPI) must be reachable.
#
# Idempotent: a stamp (libzmq source version + patch hash + pyzmq version) in
# VENV/opt/libzmq/.dran-stamp; when it matches and the venv's pyzmq has drafts, the script
# exits at once without touching the network.
#
# Environment (all optional):
#   DRAN_ZMQ_SOURCE_DIR  an unpacked libzmq 4.3.x source tree to use instead of apt-get source
#                        (offline robots: copy the tree fetched on another machine)
#   DRAN_PYZMQ_SPEC      pip requirement for pyzmq (default: pyzmq>=25)
#   DRAN_ZMQ_JOBS        parallel compile jobs (default: nproc)
#   DRAN_ZMQ_CROSS       a cross-compiler triplet (e.g. aarch64-linux-gnu): build only libzmq,
#                        with ${triplet}-gcc/g++, for that architecture (no pyzmq, no check);
#                        the offline bundle builds the robot's libzmq so (docs/bundle.md)
#   DRAN_ZMQ_PREBUILT=1  VENV/opt/libzmq already holds a libzmq built by this script (its
#                        .dran-stamp has our patch hash): build only pyzmq against it
# docs/zeromq.md describes the robot-side (Ubuntu 20.04/22.04, aarch64) procedure.
set -euo pipefail

VENV=$(cd "${1:-.venv}" && pwd)
PY="$VENV/bin/python"
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
PATCH="$HERE/patches/libzmq-udp-engine-hardening.patch"
PREFIX="$VENV/opt/libzmq"
CACHE="$VENV/opt/zmq-build"
STAMP="$PREFIX/.dran-stamp"
PYZMQ_SPEC=${DRAN_PYZMQ_SPEC:-pyzmq>=25}
JOBS=${DRAN_ZMQ_JOBS:-$(nproc 2>/dev/null || echo 2)}

log() { echo "build_zmq_draft: $*" >&2; }
die() { log "ERROR: $*"; exit 1; }

[ -x "$PY" ] || die "no python in $VENV (expected $PY); create the venv first"
[ -f "$PATCH" ] || die "patch not found: $PATCH"
PATCH_HASH=$(sha256sum "$PATCH" | cut -c1-16)

# The venv's pyzmq must have drafts and load the libzmq under PREFIX.
verify() {
    "$PY" - "$PREFIX" <<'EOF'
import sys, zmq
prefix = sys.argv[1]
assert zmq.has("draft"), "pyzmq has no draft support"
assert zmq.DRAFT_API, "zmq.DRAFT_API is False"
assert zmq.RADIO == 14 and zmq.DISH == 15, "RADIO/DISH constants missing"
ctx = zmq.Context()
try:
    dish = ctx.socket(zmq.DISH)
    dish.join("dran.check")
    dish.close(0)
finally:
    ctx.term()
with open("/proc/self/maps") as f:
    maps = f.read()
assert prefix in maps, f"pyzmq did not load the libzmq under {prefix}"
print(zmq.zmq_version(), zmq.__version__)
EOF
}

# ------------------------------------------------------------ fast path: already built
if [ -z "${DRAN_ZMQ_CROSS:-}" ] && [ -f "$STAMP" ] && grep -q "patch=$PATCH_HASH" "$STAMP" &&
   verify >/dev/null 2>&1; then
    log "up to date ($(cat "$STAMP"))"
    exit 0
fi

if [ "${DRAN_ZMQ_PREBUILT:-0}" = 1 ]; then
    grep -q "patch=$PATCH_HASH" "$STAMP" 2>/dev/null && ls "$PREFIX"/lib/libzmq.so* >/dev/null 2>&1 \
        || die "DRAN_ZMQ_PREBUILT=1 but $PREFIX holds no libzmq built with our patch ($STAMP)"
    SRC_VERSION=$(sed -n 's/^libzmq=\([^ ]*\).*/\1/p' "$STAMP")
    mkdir -p "$CACHE"
    log "using the prebuilt libzmq $SRC_VERSION in $PREFIX"
else
mkdir -p "$CACHE"

# ------------------------------------------------------------ libzmq source
fetch_with_apt() {
    local apt="$CACHE/apt"
    mkdir -p "$apt/lists/partial" "$apt/archives/partial" "$apt/cache" "$CACHE/src"
    # deb-src twins of the distribution's own archive entries (not third-party repositories
    # such as ROS's, whose URLs may contain "ubuntu" too): tools/deb_src_entries.py.
    "$PY" "$HERE/deb_src_entries.py" "$apt/sources.list.d" \
        || die "no Debian/Ubuntu archive entry found to derive deb-src lines from"
    local opts=(-o "Dir::Etc::SourceList=/dev/null" -o "Dir::Etc::SourceParts=$apt/sources.list.d"
                -o "Dir::State::Lists=$apt/lists" -o "Dir::Cache=$apt/cache"
                -o "Dir::Cache::Archives=$apt/archives" -o "Debug::NoLocking=1")
    log "fetching the zeromq3 source package (deb-src: $(tr '\n' ';' < "$apt/sources.list.d/dran-deb-src.list"))"
    apt-get "${opts[@]}" -qq update >&2 || die "apt-get update (deb-src) failed"
    rm -rf "$CACHE/src" && mkdir -p "$CACHE/src"
    (cd "$CACHE/src" && apt-get "${opts[@]}" -qq source zeromq3 >&2) \
        || die "apt-get source zeromq3 failed (is dpkg-dev installed?)"
    SRC=$(find "$CACHE/src" -mindepth 1 -maxdepth 1 -type d -name 'zeromq3-*' | head -n1)
    [ -n "$SRC" ] || die "apt-get source produced no zeromq3-* directory"
    SRC_VERSION=$(basename "$(ls "$CACHE"/src/zeromq3_*.dsc)" .dsc | sed 's/^zeromq3_//')
}

if [ -n "${DRAN_ZMQ_SOURCE_DIR:-}" ]; then
    [ -f "$DRAN_ZMQ_SOURCE_DIR/src/udp_engine.cpp" ] \
        || die "DRAN_ZMQ_SOURCE_DIR=$DRAN_ZMQ_SOURCE_DIR is not a libzmq source tree"
    rm -rf "$CACHE/src" && mkdir -p "$CACHE/src"
    cp -r "$DRAN_ZMQ_SOURCE_DIR" "$CACHE/src/libzmq"
    SRC="$CACHE/src/libzmq"
    SRC_VERSION="dir-$(sed -n 's/^#define ZMQ_VERSION_\(MAJOR\|MINOR\|PATCH\) \([0-9]*\)/\2/p' \
        "$SRC/include/zmq.h" | paste -sd.)"
else
    fetch_with_apt
fi
log "libzmq source $SRC_VERSION in $SRC"

# ------------------------------------------------------------ patch, configure, build
if (cd "$SRC" && patch -p1 -R --dry-run --quiet < "$PATCH" >/dev/null 2>&1); then
    log "patch already applied in $SRC"
else
    (cd "$SRC" && patch -p1 --forward --quiet < "$PATCH") \
        || die "our patch does not apply to libzmq $SRC_VERSION ($PATCH)"
fi

BUILD="$CACHE/build"
rm -rf "$BUILD" "$PREFIX"
log "building libzmq with drafts ($JOBS jobs)"
CROSS_ARGS=()
if [ -n "${DRAN_ZMQ_CROSS:-}" ]; then
    CROSS_ARGS=(-DCMAKE_SYSTEM_NAME=Linux "-DCMAKE_SYSTEM_PROCESSOR=${DRAN_ZMQ_CROSS%%-*}"
                "-DCMAKE_C_COMPILER=$DRAN_ZMQ_CROSS-gcc" "-DCMAKE_CXX_COMPILER=$DRAN_ZMQ_CROSS-g++"
                # optional libraries (GnuTLS for WSS, libbsd) only from the target's sysroot,
                # never this machine's: as in the target's own build without their -dev packages
                "-DCMAKE_FIND_ROOT_PATH=/usr/$DRAN_ZMQ_CROSS" -DCMAKE_FIND_ROOT_PATH_MODE_PROGRAM=NEVER
                -DCMAKE_FIND_ROOT_PATH_MODE_LIBRARY=ONLY -DCMAKE_FIND_ROOT_PATH_MODE_INCLUDE=ONLY
                -DCMAKE_FIND_ROOT_PATH_MODE_PACKAGE=ONLY -DWITH_TLS=OFF -DWITH_LIBBSD=OFF)
    # libzmq's feature checks run test programs: through qemu-user with the cross sysroot
    if command -v "qemu-${DRAN_ZMQ_CROSS%%-*}-static" >/dev/null; then
        CROSS_ARGS+=("-DCMAKE_CROSSCOMPILING_EMULATOR=qemu-${DRAN_ZMQ_CROSS%%-*}-static;-L;/usr/$DRAN_ZMQ_CROSS")
    fi
    command -v "$DRAN_ZMQ_CROSS-g++" >/dev/null || die "no $DRAN_ZMQ_CROSS-g++ (apt-get install g++-${DRAN_ZMQ_CROSS%%-*}-linux-gnu)"
fi
cmake -S "$SRC" -B "$BUILD" "${CROSS_ARGS[@]}" -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$PREFIX" \
    -DCMAKE_INSTALL_LIBDIR=lib -DENABLE_DRAFTS=ON -DBUILD_TESTS=OFF -DBUILD_STATIC=OFF \
    -DWITH_DOCS=OFF -DWITH_LIBSODIUM=OFF -DENABLE_CURVE=OFF -DWITH_PERF_TOOL=OFF \
    -DENABLE_CPACK=OFF >"$CACHE/cmake-configure.log" 2>&1 \
    || die "cmake configure failed, see $CACHE/cmake-configure.log"
cmake --build "$BUILD" -j "$JOBS" >"$CACHE/cmake-build.log" 2>&1 \
    || die "libzmq build failed, see $CACHE/cmake-build.log"
cmake --install "$BUILD" >"$CACHE/cmake-install.log" 2>&1 \
    || die "libzmq install failed, see $CACHE/cmake-install.log"
if [ -n "${DRAN_ZMQ_CROSS:-}" ]; then
    echo "libzmq=$SRC_VERSION patch=$PATCH_HASH cross=$DRAN_ZMQ_CROSS" > "$STAMP"
    log "done (libzmq only, for $DRAN_ZMQ_CROSS): $(cat "$STAMP")"
    exit 0
fi

fi
# ------------------------------------------------------------ pyzmq from source
# Built as a wheel (kept in $CACHE/wheels: the offline bundle ships it, docs/bundle.md), then
# installed from it.
log "building $PYZMQ_SPEC from source against $PREFIX"
rm -rf "$CACHE/wheels" && mkdir -p "$CACHE/wheels"
ZMQ_PREFIX="$PREFIX" ZMQ_DRAFT_API=1 LDFLAGS="-Wl,-rpath,$PREFIX/lib ${LDFLAGS:-}" \
    PKG_CONFIG_PATH="$PREFIX/lib/pkgconfig" \
    "$PY" -m pip wheel -q --disable-pip-version-check --no-cache-dir --no-deps \
    --no-binary pyzmq -w "$CACHE/wheels" "$PYZMQ_SPEC" >"$CACHE/pyzmq-build.log" 2>&1 \
    || die "pyzmq build failed, see $CACHE/pyzmq-build.log"
"$PY" -m pip install -q --disable-pip-version-check --no-index --force-reinstall --no-deps \
    "$CACHE"/wheels/pyzmq-*.whl >>"$CACHE/pyzmq-build.log" 2>&1 \
    || die "installing the built pyzmq wheel failed, see $CACHE/pyzmq-build.log"

VERSIONS=$(verify) || die "the built pyzmq does not work with drafts (see above)"
echo "libzmq=$SRC_VERSION patch=$PATCH_HASH libzmq_runtime+pyzmq=${VERSIONS// /+}" > "$STAMP"
log "done: $(cat "$STAMP")"
