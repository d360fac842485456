#!/usr/bin/env bash
# An arm64 Debian root filesystem run under qemu-user on an x86-64 machine (or natively on an
# aarch64 one): the build place of the offline bundle's C parts (tools/bundle/build_bundle.sh)
# and the test bench of tools/arm64_check.sh. Needs root.
#
#   tools/arm64_root.sh create  ROOT [SUITE [MIRROR]]   debootstrap (default bookworm, deb.debian.org)
#   tools/arm64_root.sh run     ROOT CMD...             run CMD inside (network as the host's)
#   tools/arm64_root.sh offline ROOT CMD...             run CMD inside with networking cut
#                                                       (unshare -n: loopback only)
#
# `run`/`offline` bind-mount /proc, /sys, /dev (and /dev/pts) for the command and unmount
# them afterwards. Inside, pip trusts the host's CA bundle (copied to
# /etc/ssl/certs/dran-host-ca.crt; /etc/pip.conf points at it).
# Host packages: qemu-user-static binfmt-support debootstrap (apt-get install them).
set -euo pipefail

log() { echo "arm64_root: $*" >&2; }
die() { log "ERROR: $*"; exit 1; }

[ "$(id -u)" -eq 0 ] || die "needs root (debootstrap, chroot, mounts)"

ensure_binfmt() {
    [ "$(uname -m)" = aarch64 ] && return 0
    command -v qemu-aarch64-static >/dev/null \
        || die "qemu-aarch64-static missing: apt-get install qemu-user-static binfmt-support debootstrap"
    if [ ! -e /proc/sys/fs/binfmt_misc/register ]; then
        mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
    fi
    if [ ! -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ]; then
        local conf=/usr/lib/binfmt.d/qemu-aarch64.conf
        [ -f "$conf" ] || die "$conf missing (qemu-user-static's binfmt entry)"
        # the F flag opens the interpreter now, so it works inside the chroot as well
        cat "$conf" > /proc/sys/fs/binfmt_misc/register
    fi
    grep -q enabled /proc/sys/fs/binfmt_misc/qemu-aarch64 || die "binfmt qemu-aarch64 not enabled"
}

create() {
    local root=$1 suite=${2:-bookworm} mirror=${3:-http://deb.debian.org/debian}
    ensure_binfmt
    if [ -x "$root/usr/bin/apt-get" ] && [ -f "$root/etc/debian_version" ]; then
        log "$root exists (delete it to start afresh)"
        return 0
    fi
    command -v debootstrap >/dev/null || die "debootstrap missing: apt-get install debootstrap"
    log "debootstrap --arch=arm64 $suite $root $mirror (a few minutes)"
    local t0=$SECONDS
    nice -n 15 debootstrap --arch=arm64 "$suite" "$root" "$mirror" >"$root.debootstrap.log" 2>&1 \
        || die "debootstrap failed, see $root.debootstrap.log"
    log "root filesystem ready in $((SECONDS - t0)) s"
}

prepare() {
    local root=$1
    [ -f "$root/etc/debian_version" ] || die "$root is not a root filesystem (tools/arm64_root.sh create)"
    ensure_binfmt
    cp /etc/resolv.conf "$root/etc/resolv.conf" 2>/dev/null || true
    # a throw-away root: dpkg need not fsync every file (unpacking is I/O-bound otherwise)
    mkdir -p "$root/etc/dpkg/dpkg.cfg.d"
    echo force-unsafe-io > "$root/etc/dpkg/dpkg.cfg.d/dran-unsafe-io"
    if [ -f /etc/ssl/certs/ca-certificates.crt ]; then
        mkdir -p "$root/etc/ssl/certs"
        cp /etc/ssl/certs/ca-certificates.crt "$root/etc/ssl/certs/dran-host-ca.crt"
        printf '[global]\ncert = /etc/ssl/certs/dran-host-ca.crt\ndisable-pip-version-check = true\n' \
            > "$root/etc/pip.conf"
    fi
}

MOUNTED=()
mount_all() {
    local root=$1 d
    for d in proc sys dev dev/pts; do
        mkdir -p "$root/$d"
        if ! mountpoint -q "$root/$d"; then
            mount --bind "/$d" "$root/$d"
            MOUNTED=("$root/$d" "${MOUNTED[@]}")
        fi
    done
}
umount_all() {
    local m
    for m in "${MOUNTED[@]}"; do umount "$m" 2>/dev/null || umount -l "$m" 2>/dev/null || true; done
    MOUNTED=()
}

in_root() {
    local mode=$1 root=$2; shift 2
    prepare "$root"
    trap umount_all EXIT
    mount_all "$root"
    local env=(env -i HOME=/root PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
               LANG=C.UTF-8 DEBIAN_FRONTEND=noninteractive OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
               TERM=dumb)
    local rc=0
    if [ "$mode" = offline ]; then
        # a fresh network namespace: no interface but loopback, which is brought up (tests and
        # the daemon use 127.0.0.1)
        unshare -n -- sh -c 'ip link set lo up && exec chroot "$@"' sh "$root" "${env[@]}" "$@" || rc=$?
    else
        chroot "$root" "${env[@]}" "$@" || rc=$?
    fi
    umount_all
    trap - EXIT
    return $rc
}

cmd=${1:-}; shift || true
case "$cmd" in
    create) [ $# -ge 1 ] || die "usage: create ROOT [SUITE [MIRROR]]"; create "$@" ;;
    run|offline) [ $# -ge 2 ] || die "usage: $cmd ROOT CMD..."; in_root "$cmd" "$@" ;;
    *) sed -n '2,16p' "$0" >&2; exit 2 ;;
esac
