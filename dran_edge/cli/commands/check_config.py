"""``dran-edge check-config FILE``: validate a robot config and show what it resolves to."""

from __future__ import annotations

import argparse

HELP = "validate a robot config file (strict: unknown keys, types, ranges)"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Load FILE exactly as 'dran-edge run' does. Prints a one-line summary and "
                    "exits 0 when valid; otherwise prints the file, line, key path and reason "
                    "and exits 2.",
    )
    p.add_argument("file", metavar="FILE", help="the robot's YAML config (docs/config.md)")
    p.add_argument("--show", action="store_true",
                   help="print the full config with every default filled in")
    return p


def run(args: argparse.Namespace) -> int:
    from dran_edge.config import config_to_dict, load_config

    cfg = load_config(args.file)
    g = cfg.agent.graph
    print(f"{args.file}: ok: robot {cfg.robot.name} (id {cfg.robot.id}) in fleet "
          f"{cfg.robot.fleet}; {len(cfg.neighbours)} neighbours; transport "
          f"{cfg.comms.transport}; camera {cfg.camera.source}; ingest "
          f"{'on' if cfg.ingest.enabled else 'off'}; graph <= {g.max_nodes} nodes / "
          f"{g.max_edges} edges")
    if args.show:
        import yaml

        print(yaml.safe_dump(config_to_dict(cfg), sort_keys=False), end="")
    return 0
