"""``dran-edge status``: ask the running daemon for its health."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dran_edge.daemon.status import query_status

HELP = "show the running daemon's health (neighbours, bytes, rounds, graph, drops)"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Connect to the daemon's status socket and print its health. The socket is "
        "<runtime dir>/status.sock (/run/dran-edge/status.sock under systemd).",
    )
    p.add_argument("--config", metavar="ROBOT.yaml", help="find the socket from this config")
    p.add_argument("--socket", metavar="PATH", help="the status socket path")
    p.add_argument("--json", action="store_true", help="print the raw JSON document")
    return p


def _neighbour_line(peer: str, n: dict) -> str:
    """One neighbour: who, when last heard ("never heard" until a datagram is accepted), bytes."""
    ago = n.get("last_heard_s_ago")
    heard = "never heard" if ago is None else f"heard {ago:.1f} s ago"
    who = f"{n['name']} (id {peer})" if n.get("name") else f"id {peer}"
    rest = "  ".join(f"{k} {v}" for k, v in n.items() if k not in ("name", "last_heard_s_ago"))
    return f"neighbour  {who}: {heard}  {rest}"


def format_status(st: dict) -> str:
    r = st.get("rounds", {})
    g = st.get("graph") or {}
    lines = [
        f"robot      {st['robot']['name']} (id {st['robot']['id']}, fleet {st['robot']['fleet']})"
        f"  state {st['state']}  pid {st.get('pid')}  boot epoch {st.get('boot_epoch')}",
        f"uptime     {st.get('uptime_s', 0):.1f} s",
        f"rounds     {r.get('ticks', 0)}  late {r.get('late', 0)}  missed {r.get('missed', 0)}"
        f"  lag max {1e3 * r.get('lag_max_s', 0):.1f} ms  solve last/mean/max "
        f"{1e3 * r.get('solve_last_s', 0):.1f}/{1e3 * r.get('solve_mean_s', 0):.1f}/"
        f"{1e3 * r.get('solve_max_s', 0):.1f} ms  agent errors {r.get('agent_errors', 0)}",
        f"graph      keyframes {g.get('keyframes', 0)}  objects {g.get('objects', 0)}"
        f"  cost {g.get('cost', float('nan')):.4g}"
        f"  consensus error {g.get('consensus_error', float('nan')):.3g}",
    ]
    nbrs = st.get("neighbours") or {}
    if nbrs:
        for peer, n in nbrs.items():
            lines.append(_neighbour_line(peer, n))
    else:
        lines.append(
            "neighbours none configured"
            if st.get("transport")
            else "neighbours none (no radio: comms.transport none)"
        )
    t = st.get("transport") or {}
    if t:
        lines.append(
            "transport  " + "  ".join(f"{k} {v}" for k, v in t.items() if k != "neighbours")
        )
    ing = st.get("ingest")
    if ing:
        rej = ing.get("rejected_by_reason") or {}
        lines.append(
            f"ingest     records {ing.get('records', 0)}  bytes {ing.get('bytes', 0)}"
            f"  frames {ing.get('frames', 0)}  rejected {ing.get('rejected', 0)}"
            + (" (" + ", ".join(f"{k} {v}" for k, v in sorted(rej.items())) + ")" if rej else "")
        )
    else:
        lines.append("ingest     off")
    q = st.get("queues", {})
    lines.append(
        f"queues     observations dropped {q.get('observations_dropped', 0)}"
        f"  frames dropped {q.get('frames_dropped', 0)}"
        f"  journal pending {st.get('journal', {}).get('pending', 0)}"
    )
    lines.append(f"systemd    {st.get('systemd')}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.socket:
        path = Path(args.socket)
    elif args.config:
        from dran_edge.config import load_config
        from dran_edge.daemon.service import resolve_dirs

        _, runtime = resolve_dirs(load_config(args.config))
        path = runtime / "status.sock"
    else:
        path = Path("/run/dran-edge/status.sock")
    st = query_status(path)
    print(json.dumps(st, indent=2) if args.json else format_status(st))
    return 0
