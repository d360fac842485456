"""``dran-edge fleet-key``: create and check the keys that authenticate neighbour datagrams.

Key policies (``comms.auth``; docs/wire-format.md, "Authentication"): ``hmac`` (one fleet
key: ``new``, ``check``) and ``ed25519`` / ``pairwise`` (one key pair per robot, the same files
for both: ``pair`` on each robot, ``export`` the public halves into the fleet's public-key file,
``check``).
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

HELP = "create or check the keys that authenticate neighbour datagrams (fleet or per robot)"


def build_parser(prog: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Keys for the key policies of comms.auth (docs/wire-format.md).\n\n"
            "hmac (one secret per fleet; any robot holding it can sign as any other):\n"
            "  new PATH           write a random 32-byte fleet key (mode 0600); copy it to every\n"
            "                     robot (keep the mode)\n\n"
            "ed25519 and pairwise (one key pair per robot; a robot can send only as itself;\n"
            "pairwise agrees an HMAC key per pair of robots from the same key pairs):\n"
            "  pair PATH --robot-id N\n"
            "                     write robot N's secret key to PATH (mode 0600; it never leaves\n"
            "                     the robot) and its public key to PATH.pub\n"
            "  export OUT --fleet NAME PUB_OR_DIR...\n"
            "                     collect robots' PATH.pub files (or every *.pub in a directory)\n"
            "                     into the fleet's public-key file OUT; copy OUT to every robot\n"
            "                     (comms.public_keys_file). Two .pub files of one robot (old and\n"
            "                     new key while it rotates) give both keys.\n\n"
            "  check PATH         load a fleet key, a robot secret key, a .pub file or a fleet\n"
            "                     public-key file as the daemon does and print what it holds\n"
            "                     (fingerprints to compare across robots)."
        ),
    )
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    new = sub.add_parser("new", help="write a new fleet HMAC key")
    new.add_argument("path", metavar="PATH", help="the key file to create")
    chk = sub.add_parser("check", help="load a key file as the daemon does")
    chk.add_argument("path", metavar="PATH", help="the key file")
    pair = sub.add_parser("pair", help="write a robot's Ed25519 key pair (PATH, PATH.pub)")
    pair.add_argument("path", metavar="PATH", help="the secret key file to create")
    pair.add_argument(
        "--robot-id",
        type=int,
        required=True,
        metavar="N",
        help="the robot's id (robot.id of its config)",
    )
    exp = sub.add_parser("export", help="write the fleet's public-key file from .pub files")
    exp.add_argument("out", metavar="OUT", help="the fleet public-key file to write")
    exp.add_argument(
        "--fleet", required=True, metavar="NAME", help="the fleet's name (robot.fleet)"
    )
    exp.add_argument(
        "inputs",
        nargs="+",
        metavar="PUB_OR_DIR",
        help="robots' .pub files, or directories holding them",
    )
    return parser


def _fingerprint(key: bytes, label: bytes = b"dran-edge fleet key") -> str:
    return hashlib.sha256(label + key).hexdigest()[:16]


def _check(path: str) -> str:
    from dran_edge.comms import keys
    from dran_edge.errors import ConfigError

    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ConfigError(f"cannot read the key file: {exc.strerror}", path=path) from None
    if "public_keys:" in text:
        fleet, table = keys.load_fleet_public_keys(path)
        rows = ", ".join(
            f"{rid}: {len(ks)} key{'s' * (len(ks) > 1)}" for rid, ks in sorted(table.items())
        )
        return f"ok {path}: fleet {fleet!r} public keys of {len(table)} robots ({rows})"
    if "public_key:" in text:
        rid, public = keys.load_public_key_file(path)
        return f"ok {path}: robot {rid}'s public key {public.hex()}"
    if "ed25519-secret" in text:
        public = keys.public_key_of(keys.load_robot_key(path))
        return f"ok {path}: robot secret key (Ed25519), public key {public.hex()}"
    key = keys.load_fleet_key(path)
    return f"ok {path}: {len(key)}-byte key, fingerprint {_fingerprint(key)}"


def _export(out: str, fleet: str, inputs: list[str]) -> str:
    from dran_edge.comms import keys
    from dran_edge.errors import ConfigError

    files: list[Path] = []
    for item in inputs:
        p = Path(item)
        files.extend(sorted(p.glob("*.pub")) if p.is_dir() else [p])
    if not files:
        raise ConfigError("no .pub files found", path=", ".join(inputs))
    table: dict[int, tuple[bytes, ...]] = {}
    for f in files:
        rid, public = keys.load_public_key_file(f)
        table[rid] = tuple(dict.fromkeys(table.get(rid, ()) + (public,)))
    keys.write_fleet_public_keys(out, fleet, table)
    return f"wrote {out}: fleet {fleet!r}, public keys of robots {sorted(table)}"


def run(args: argparse.Namespace) -> int:
    from dran_edge.comms import keys

    if args.action == "new":
        key = keys.write_fleet_key(args.path)
        print(f"wrote {args.path}: {len(key)}-byte key, fingerprint {_fingerprint(key)}")
    elif args.action == "pair":
        public = keys.write_robot_key(args.path, args.robot_id)
        print(
            f"wrote {args.path} (secret, mode 0600) and {keys.public_key_path(args.path)}: "
            f"robot {args.robot_id}'s public key {public.hex()}"
        )
    elif args.action == "export":
        print(_export(args.out, args.fleet, args.inputs))
    else:
        print(_check(args.path))
    return 0
