"""``dran-edge fleet-key``: create or check the fleet's HMAC key file (docs/wire-format.md)."""

from __future__ import annotations

import argparse
import hashlib

HELP = "create or check the fleet key that authenticates neighbour datagrams"


def build_parser(prog: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Every neighbour datagram carries an HMAC-SHA256 tag made with one secret key per "
            "fleet. 'new' writes a fresh random 32-byte key as hex to PATH with mode 0600 "
            "(refusing to overwrite); copy that file to every robot of the fleet (keep the "
            "mode). 'check' loads PATH as the daemon does (mode must give no group/other "
            "access) and prints a fingerprint to compare across robots."
        ),
    )
    parser.add_argument("action", choices=("new", "check"))
    parser.add_argument("path", metavar="PATH", help="the key file")
    return parser


def run(args: argparse.Namespace) -> int:
    from dran_edge.comms.auth import load_fleet_key, write_fleet_key

    key = write_fleet_key(args.path) if args.action == "new" else load_fleet_key(args.path)
    fingerprint = hashlib.sha256(b"dran-edge fleet key" + key).hexdigest()[:16]
    verb = "wrote" if args.action == "new" else "ok"
    print(f"{verb} {args.path}: {len(key)}-byte key, fingerprint {fingerprint}")
    return 0
