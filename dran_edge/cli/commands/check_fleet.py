"""``dran-edge check-fleet DIR``: check a directory of robot configs for consistency.

Each robot's file may be valid alone while the fleet is not: robots that disagree on the fleet
name (their datagrams are dropped as ``wrong_fleet``), list each other one-sidedly (one side
drops the other's datagrams as ``not_neighbour``), share an id or an address, or use different
key policies or keys. This command loads every ``*.yaml`` / ``*.yml`` in DIR that has a
``robot`` section and reports every such problem.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from dran_edge.errors import ConfigError, DranError

HELP = "check a directory of robot configs for consistency (fleet, neighbours, ids, keys)"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Load every robot config (*.yaml with a 'robot' section) in DIR and check "
        "that they form one fleet: the same fleet name; unique robot ids, names "
        "and addresses; every neighbour entry names a robot of DIR with its name, "
        "its address matching that robot's port, and the neighbour lists it back; "
        "one key policy (comms.auth); with hmac the same fleet key where the key "
        "files are readable; with ed25519 or pairwise each robot's public key (from its key "
        "file's .pub) in every neighbour's keys. Also the same agent.dim, "
        "comms.period_s, agent.beta and agent.eta (the consensus duals of a pair balance "
        "only with one beta and eta). Prints every problem and exits 2, or a summary and 0.",
    )
    p.add_argument("dir", metavar="DIR", help="the directory of robot configs (e.g. calib/fleet)")
    return p


@dataclass
class FleetReport:
    """What ``check_fleet`` found: the robots loaded, problems (errors) and notes."""

    robots: dict = field(default_factory=dict)  # robot id -> config
    errors: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    def error(self, text: str, path: str | None = None) -> None:
        self.errors.append(ConfigError(text, path=path))


def _load_dir(directory: Path, rep: FleetReport) -> list:
    import yaml

    from dran_edge.config import load_config_report

    files = sorted(p for p in directory.iterdir() if p.suffix in (".yaml", ".yml") and p.is_file())
    cfgs = []
    for path in files:
        try:
            doc = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError):
            doc = None
        if not isinstance(doc, dict) or "robot" not in doc:
            rep.notes.append(f"{path.name}: not a robot config (no 'robot' section), skipped")
            continue
        cfg, errors = load_config_report(path)
        rep.errors.extend(errors)
        if cfg is not None:
            cfgs.append(cfg)
    if not cfgs:
        rep.error("no robot configs found", path=str(directory))
    return cfgs


def _identity(cfgs: list, rep: FleetReport) -> None:
    fleets = defaultdict(list)
    ids = defaultdict(list)
    names = defaultdict(list)
    for c in cfgs:
        fleets[c.robot.fleet].append(Path(c.source_path).name)
        ids[c.robot.id].append(Path(c.source_path).name)
        names[c.robot.name].append(Path(c.source_path).name)
    if len(fleets) > 1:
        rep.error(
            "robots disagree on the fleet name: "
            + "; ".join(f"{f!r} in {', '.join(fs)}" for f, fs in sorted(fleets.items()))
        )
    for what, table in (("id", ids), ("name", names)):
        for value, fs in sorted(table.items(), key=lambda kv: str(kv[0])):
            if len(fs) > 1:
                rep.error(f"robot {what} {value} is used by {len(fs)} configs: {', '.join(fs)}")
    rep.robots = {c.robot.id: c for c in cfgs}
    for what, get in (
        ("agent.dim", lambda c: c.agent.dim),
        ("comms.period_s", lambda c: c.comms.period_s),
        # the dual step η β w of eq. 5b must be the same at both ends of a pair, or the duals'
        # sum λ_ij + λ_ji drifts off zero and the consensus settles off the optimum
        ("agent.beta", lambda c: c.agent.beta),
        ("agent.eta", lambda c: c.agent.eta),
    ):
        values = defaultdict(list)
        for c in cfgs:
            values[get(c)].append(c.robot.name)
        if len(values) > 1:
            rep.error(
                f"robots disagree on {what}: "
                + "; ".join(f"{v} ({', '.join(n)})" for v, n in sorted(values.items()))
            )
    for c in cfgs:  # block SOR assumes synchronous lossless rounds (docs/config.md)
        if c.agent.sor_omega != 1.0:
            rep.error(
                f"agent.sor_omega is {c.agent.sor_omega:g}: over-relaxation needs every "
                "neighbour's newest values each round and diverged over lossy links in the "
                "benches; a fleet over WiFi uses 1",
                path=c.source_path,
            )


def _neighbours(cfgs: list, rep: FleetReport) -> None:
    from dran_edge.config import parse_address

    robots = rep.robots
    listed_at = defaultdict(set)  # robot id -> addresses others list it at
    for c in cfgs:
        where = c.source_path
        for n in c.neighbours:
            other = robots.get(n.id)
            if other is None:
                rep.error(
                    f"neighbour {n.id} ({n.name or 'no name'}) is not a robot of this directory",
                    path=where,
                )
                continue
            if n.name and n.name != other.robot.name:
                rep.error(
                    f"neighbour {n.id} is named {n.name!r} here but {other.robot.name!r} "
                    "in its own config",
                    path=where,
                )
            if c.robot.id not in {m.id for m in other.neighbours}:
                rep.error(
                    f"lists {other.robot.name} (id {n.id}) as a neighbour, but "
                    f"{Path(other.source_path).name} does not list {c.robot.name} "
                    f"(id {c.robot.id}) back: {other.robot.name} drops its datagrams "
                    "as not_neighbour",
                    path=where,
                )
            host, port = parse_address(n.address, "address")
            listed_at[n.id].add((host, port))
            if port != other.comms.port:
                rep.error(
                    f"neighbour {other.robot.name}'s address {n.address} has port {port}, "
                    f"but it binds port {other.comms.port}",
                    path=where,
                )
            bind = other.comms.bind_address
            if bind not in ("0.0.0.0", "::") and bind != host:
                rep.error(
                    f"neighbour {other.robot.name}'s address {n.address}, but it binds {bind}",
                    path=where,
                )
    owners = defaultdict(set)
    for rid, addrs in listed_at.items():
        if len(addrs) > 1:
            rep.error(
                f"robot {robots[rid].robot.name} (id {rid}) is listed at different "
                f"addresses: {', '.join(f'{h}:{p}' for h, p in sorted(addrs))}"
            )
        for a in addrs:
            owners[a].add(rid)
    for (host, port), rids in sorted(owners.items()):
        if len(rids) > 1:
            rep.error(f"address {host}:{port} is given to robots {sorted(rids)}")


def _own_public_key(c) -> bytes | None:
    """A robot's own public key from its key file's .pub (or the secret, where readable)."""
    from dran_edge.comms import keys

    path = c.resolve(c.comms.key_file)
    if path is None:
        return None
    pub = Path(keys.public_key_path(path))
    try:
        if pub.is_file():
            rid, key = keys.load_public_key_file(pub)
            return key if rid == c.robot.id else None
        return keys.public_key_of(keys.load_robot_key(path))
    except DranError:
        return None


def _keys(cfgs: list, rep: FleetReport) -> None:
    from dran_edge.comms import keys

    radio = [c for c in cfgs if c.comms.transport != "none"]
    policies = defaultdict(list)
    for c in radio:
        policies[c.comms.auth].append(c.robot.name)
    if len(policies) > 1:
        rep.error(
            "robots use different key policies (comms.auth): "
            + "; ".join(f"{p} ({', '.join(n)})" for p, n in sorted(policies.items()))
        )
        return
    if policies.get("hmac"):
        prints = defaultdict(list)
        for c in radio:
            try:
                prints[keys.load_fleet_key(c.resolve(c.comms.key_file)).hex()].append(c.robot.name)
            except (DranError, TypeError):
                rep.notes.append(f"{c.robot.name}: fleet key not readable here, not compared")
        if len(prints) > 1:
            rep.error(
                "robots hold different fleet keys: "
                + "; ".join(f"key {i + 1} ({', '.join(n)})" for i, n in enumerate(prints.values()))
            )
        return
    for c in radio:
        own = _own_public_key(c)
        if own is None:
            rep.notes.append(
                f"{c.robot.name}: own public key not found (no readable "
                f"{c.comms.key_file}.pub), only presence in neighbours checked"
            )
        for n in c.neighbours:
            other = rep.robots.get(n.id)
            if other is None or other.comms.transport == "none":
                continue
            try:
                held = keys.fleet_public_keys(other).get(c.robot.id, ())
            except DranError as exc:
                rep.errors.append(exc)
                continue
            if not held:
                rep.error(
                    f"has no public key for {c.robot.name} (id {c.robot.id}), its "
                    "neighbour: it drops all of its datagrams",
                    path=other.source_path,
                )
            elif own is not None and own not in held:
                rep.error(
                    f"holds a public key for {c.robot.name} (id {c.robot.id}) that is not "
                    f"{c.robot.name}'s own (export the fleet's keys again)",
                    path=other.source_path,
                )


def check_fleet(directory: str | Path) -> FleetReport:
    """Every consistency problem of the robot configs in ``directory``."""
    rep = FleetReport()
    directory = Path(directory)
    if not directory.is_dir():
        rep.error("expected a directory of robot configs", path=str(directory))
        return rep
    cfgs = _load_dir(directory, rep)
    if cfgs:
        _identity(cfgs, rep)
        _neighbours(cfgs, rep)
        _keys(cfgs, rep)
    return rep


def run(args: argparse.Namespace) -> int:
    rep = check_fleet(args.dir)
    for note in rep.notes:
        print(f"note: {note}")
    for e in rep.errors:
        print(f"dran-edge check-fleet: error: {e}", file=sys.stderr)
    if rep.errors:
        print(
            f"{args.dir}: {len(rep.errors)} problem{'s' * (len(rep.errors) != 1)}", file=sys.stderr
        )
        return 2
    cfgs = list(rep.robots.values())
    links = sum(len(c.neighbours) for c in cfgs) // 2
    policy = sorted({c.comms.auth for c in cfgs if c.comms.transport != "none"}) or ["no radio"]
    print(
        f"{args.dir}: ok: fleet {cfgs[0].robot.fleet}, {len(cfgs)} robots, {links} links, "
        f"key policy {policy[0]}"
    )
    return 0
