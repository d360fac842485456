#!/usr/bin/env bash
# Proof that the offline bundle installs and works on aarch64: an arm64 Debian 12 root
# filesystem under qemu-user (tools/arm64_root.sh), the bundle installed into it with the
# network cut (unshare -n), then, still offline:
#   1. `dran-edge run --config fleet/laptop.yaml` for a few rounds (stopped with SIGINT);
#   2. `dran-edge simulate` (small, --frames none) + `dran-edge replay` of it;
#   3. the test suite from the checkout (a subset by default; ARM64_CHECK_FULL=1 for all),
#      minus what cannot run emulated (listed with the reason below).
# Not part of `make test` (tens of minutes under emulation). Needs root and `make bundle` first.
#
#   sudo tools/arm64_check.sh [BUNDLE.tar.gz]     (default: the newest dist/*-aarch64.tar.gz)
#
# Environment: ARM64_CHECK_ROOT (default /var/tmp/dran-arm64/check-root; created by
# debootstrap, or copied from ARM64_PRISTINE_ROOT when that is set), ARM64_CHECK_FULL=1.
# The robot's base system is assumed to have python3 + python3-venv (JetPack has them): they
# are apt-installed into the root *before* the network is cut. Test-only packages (pytest,
# hypothesis, matplotlib for the plots) are downloaded on the host as aarch64 wheels and
# installed offline into a second venv layered on the bundle's, so the robot venv stays as
# install.sh made it. Result: dist/arm64_check/result.txt (+ logs).
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
BUNDLE=${1:-$(ls -t "$REPO"/dist/dran-edge-*-aarch64.tar.gz 2>/dev/null | sed -n 1p)}
ROOT=${ARM64_CHECK_ROOT:-/var/tmp/dran-arm64/check-root}
OUT=$REPO/dist/arm64_check
# the host's Python downloads the test-only aarch64 wheels: the checkout's venv when there is
# one (make setup), else python3 with pip (a fresh clone after `make bundle` has no venv)
HOSTPY=${PYTHON:-$([ -x "$REPO/.venv/bin/python" ] && echo "$REPO/.venv/bin/python" || command -v python3 || true)}
R="bash $REPO/tools/arm64_root.sh"
log() { echo "arm64_check: $*" >&2; }
die() { log "ERROR: $*"; exit 1; }
[ -f "$BUNDLE" ] || die "no bundle (make bundle first, or pass BUNDLE.tar.gz)"
[ -n "$HOSTPY" ] && "$HOSTPY" -m pip --version >/dev/null 2>&1 \
    || die "no host Python with pip (${HOSTPY:-python3}): install python3-pip, or set PYTHON=/path/to/python"
NAME=$(basename "$BUNDLE" .tar.gz)
PYV=$(tar -xzOf "$BUNDLE" "$NAME/BUNDLE_INFO" | sed -n 's/^python=//p')
mkdir -p "$OUT"
RESULT=$OUT/result.txt
: > "$RESULT"
note() { echo "$*" | tee -a "$RESULT" >&2; }
t0=$SECONDS
note "arm64 check of $NAME on $(date -u +%Y-%m-%dT%H:%M:%SZ), commit $(git -C "$REPO" rev-parse --short HEAD)"

# ------------------------------------------------------------------ the root (network on)
if [ ! -f "$ROOT/etc/debian_version" ]; then
    if [ -n "${ARM64_PRISTINE_ROOT:-}" ]; then
        log "copying $ARM64_PRISTINE_ROOT -> $ROOT"
        cp -a "$ARM64_PRISTINE_ROOT" "$ROOT"
    else
        $R create "$ROOT"
    fi
fi
$R run "$ROOT" sh -c 'dpkg-query -W -f="\${Status}" python3-venv 2>/dev/null | grep -q "ok installed" ||
    { apt-get update -qq && apt-get install -y -qq --no-install-recommends python3 python3-venv >/dev/null; }'
note "root ready (python3 + python3-venv, the robot's base): $((SECONDS - t0)) s"

# test-only wheels for aarch64 (host download; installed offline below)
TW=$ROOT/opt/test-wheels
mkdir -p "$TW"
"$HOSTPY" -m pip download -q --disable-pip-version-check --only-binary=:all: --implementation cp \
    --python-version "$PYV" --platform manylinux2014_aarch64 --platform manylinux_2_17_aarch64 \
    --platform manylinux_2_28_aarch64 -d "$TW" pytest hypothesis "matplotlib>=3.7" \
    "numpy==$(tar -xzOf "$BUNDLE" "$NAME/requirements.txt" | sed -n 's/^numpy==//p')" >/dev/null

# the bundle and the checkout's tests (no dran_edge/ sources: the tests import the installed wheel)
rm -rf "$ROOT/opt/bundle" "$ROOT/opt/src" "$ROOT/opt/dran-edge" "$ROOT/etc/dran-edge" "$ROOT/tmp/check"
mkdir -p "$ROOT/opt/bundle" "$ROOT/opt/src" "$ROOT/tmp/check"
tar -C "$ROOT/opt/bundle" -xzf "$BUNDLE"
cp -r "$REPO/tests" "$REPO/tools" "$REPO/calib" "$REPO/pyproject.toml" "$ROOT/opt/src/"

offline() { $R offline "$ROOT" "$@"; }

# ------------------------------------------------------------------ offline from here on
t1=$SECONDS
offline sh -c "python3 -c 'import urllib.request as u; u.urlopen(\"https://pypi.org\", timeout=5)' \
    2>/dev/null && echo NETWORK-UP || echo network-cut" | tee "$OUT/network.txt"
grep -qx network-cut "$OUT/network.txt" || die "the network is not cut inside the check"
offline nice -n 15 "/opt/bundle/$NAME/install.sh" --no-systemd --robot dingo1 2>&1 | tee "$OUT/install.log"
note "install.sh (offline): $((SECONDS - t1)) s; its notes:"
grep -E "NOTE|Left to do|^  - " "$OUT/install.log" | sed 's/^/    /' | tee -a "$RESULT" >&2 || true

t2=$SECONDS
offline sh -c 'cd /tmp/check && timeout -s INT 40 /opt/dran-edge/.venv/bin/dran-edge run \
    --config /etc/dran-edge/fleet/laptop.yaml; echo "exit $?"' > "$OUT/run.log" 2>&1 || true
rounds=$(sed -n 's/.*stopped after \([0-9]*\) rounds.*/\1/p' "$OUT/run.log")
[ "${rounds:-0}" -ge 3 ] || { cat "$OUT/run.log" >&2; die "dran-edge run did not complete rounds"; }
note "dran-edge run (laptop.yaml, SIGINT after 40 s): $rounds rounds, $((SECONDS - t2)) s"

t3=$SECONDS
offline sh -c 'cd /tmp/check && D=/opt/dran-edge/.venv/bin/dran-edge &&
    $D simulate sim --robots 2 --objects 4 --duration-s 20 --frames none --seed 3 &&
    $D replay sim --settle-rounds 5' > "$OUT/replay.log" 2>&1 || { cat "$OUT/replay.log" >&2; die "simulate/replay failed"; }
note "dran-edge simulate + replay (2 robots, 20 s, --frames none): $((SECONDS - t3)) s"
grep -E "^(replayed|SR_ATE)" "$OUT/replay.log" | sed 's/^/    /' | tee -a "$RESULT" >&2

# ------------------------------------------------------------------ tests (offline)
# Not runnable emulated, deselected:
#  - tests marked hardware (no RealSense/OAK/Jetson) and slow (as in make test);
#  - tests marked network: they create network namespaces / veth pairs with `ip netns`, which
#    failed in an emulated root (issue 25's first run); not attempted here;
#  - tests/test_vins_bridge.py: needs ROS (rospy) from apt, not part of a robot bundle;
#  - (full suite) timing assertions at a 50 ms daemon period (test_daemon's deadlines) can fail
#    under emulation, which runs Python about 10x slower: such a failure is emulation, not arm64.
SKIP=(--deselect tests/test_vins_bridge.py)
if [ "${ARM64_CHECK_FULL:-0}" = 1 ]; then
    SEL=(tests)
else  # the subset (the full suite takes 12+ minutes under qemu on an idle machine): the golden
      # replay of the recorded run (and the damping's cost resolution it relies on), the
      # detector, the wire codec, RADIO/DISH over the bundle's libzmq, the offline driver
      # install, the deb-src rule; re-detection is measured by
      # tools/redetect_diff.py below (what tests/test_replay.py's tolerance test asserts)
    SEL=(tests/test_replay.py::test_matches_the_golden_summary
         tests/test_damping.py tests/test_perception_detector.py
         tests/test_codec.py tests/test_radio.py tests/test_install_drivers.py
         tests/test_deb_src.py)
fi
t4=$SECONDS
offline sh -c "set -e; /opt/dran-edge/.venv/bin/python -m venv --system-site-packages /opt/testenv 2>/dev/null || true
    cat > /opt/testenv/lib/python$PYV/site-packages/robot-venv.pth <<EOF
/opt/dran-edge/.venv/lib/python$PYV/site-packages
EOF
    /opt/testenv/bin/python -m pip install -q --no-index --find-links /opt/test-wheels pytest hypothesis matplotlib
    cd /opt/src && OPENBLAS_NUM_THREADS=1 PATH=/opt/dran-edge/.venv/bin:\$PATH nice -n 15 \
    /opt/testenv/bin/python -m pytest -q -p no:cacheprovider -m 'not slow and not hardware and not network' \
    ${SKIP[*]} ${SEL[*]}" > "$OUT/pytest.log" 2>&1 && ok=1 || ok=0
tail -n 25 "$OUT/pytest.log" >&2
note "pytest ($([ "${ARM64_CHECK_FULL:-0}" = 1 ] && echo full suite || echo "subset: ${SEL[*]}"), offline, emulated): $(tail -n1 "$OUT/pytest.log"), $((SECONDS - t4)) s"
# what re-detection changes here against the x86-64 recording (the tolerance test's numbers)
t5=$SECONDS
offline sh -c "cd /opt/src && OPENBLAS_NUM_THREADS=1 nice -n 15 /opt/testenv/bin/python tools/redetect_diff.py" \
    > "$OUT/redetect.log" 2>&1 || true
note "re-detection of the tiny golden run here vs its x86-64 recording ($((SECONDS - t5)) s):"
sed 's/^/    /' "$OUT/redetect.log" | tail -n 4 | tee -a "$RESULT" >&2
note "total: $((SECONDS - t0)) s"
[ "$ok" = 1 ] || die "tests failed (dist/arm64_check/pytest.log)"
log "passed; summary in $RESULT"
