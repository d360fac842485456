"""What one exchange of every separator costs on the wire, against the Table 1 byte bars.

Usage: .venv/bin/python tools/bench/table1_floor.py DATA_DIR [--robots 5] [--only NAME ...]

For each graph of Table 1, split like the bench (``partition.partition_contiguous``), every
robot sends every neighbour each of its poses that neighbour's inter-robot edges touch — one
*full exchange*, the least a block iteration (DRAN, DGS, either init stage) moves per sweep
when every separator has changed. The messages are encoded by the real codec
(``comms.codec.encode_datagrams``, 1200-byte datagrams, header and 16-byte tag slot included):

- ``absolute``: pose entries as sent the first time (float32 translation, packed rotation);
- ``delta``: the same entries as delta-layout changes (``comms.delta``: int8 exponent + one int8
  per component, the smallest entry the wire has), primed by an absolute round;
- ``init rot``: the rotation stage's relaxed d×d matrices as delta entries.

``bar / delta`` is how many such sweeps the issue's byte bar (half the paper's DRAN column)
pays for in total, the initialisation included. Nothing here runs an optimiser: the number of
sweeps each graph needs is measured by ``bench_table1.py`` / ``trace_g2o.py``
(docs/benchmarks.md, Table 1).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: see docs/benchmarks.md

import argparse
import sys
from pathlib import Path

import numpy as np

from dran_edge import geometry as geo
from dran_edge.comms import codec
from dran_edge.comms.delta import DeltaEncoder
from dran_edge.formats.g2o import read_g2o
from dran_edge.messages import InitEntry, InitStage, NeighbourMessage, SeparatorEntry
from dran_edge.experiments.fleet import ROUND_PERIOD_NS, TABLE1_DELTA_EVERY
from dran_edge.dran.partition import partition_contiguous

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_table1 import PAPER  # noqa: E402 - the paper's columns, in one place


def byte_bar_mb(name: str) -> float:
    """The issue's byte bar: half the paper's DRAN column."""
    return PAPER[name][5] / 2


def _bytes(messages: list[NeighbourMessage], encoders: list[DeltaEncoder | None]) -> int:
    return sum(len(d.data) for m, enc in zip(messages, encoders)
               for d in codec.encode_datagrams(m, fleet_id=1, boot_epoch=1, first_sequence=0,
                                               delta=enc))


def full_exchange_bytes(g, num_robots: int) -> dict:
    """Bytes of one full separator exchange (absolute, delta) and of one relaxed-rotation
    exchange (delta), summed over every directed link of the split."""
    part = partition_contiguous(g.edges, g.num_vertices, num_robots)
    rng = np.random.default_rng(0)
    # (sender, receiver, the sender's vertices the receiver needs), as the init sends them
    links = [(p.robot_id, q, vs) for p in part.parts for q, vs in p.separators_for.items()
             if len(vs)]

    def separators(round_, poses):
        return [NeighbourMessage(sender_id=s, round=round_, stamp_ns=round_ * ROUND_PERIOD_NS,
                                 separators=tuple(SeparatorEntry(s, int(v), 0, poses[v])
                                                  for v in need))
                for s, _r, need in links]

    def rotations(round_, R):
        return [NeighbourMessage(sender_id=s, round=round_, stamp_ns=round_ * ROUND_PERIOD_NS,
                                 init=tuple(InitEntry(InitStage.ROTATION, s, int(v), R[v])
                                            for v in need))
                for s, _r, need in links]

    poses = np.asarray(g.poses, np.float64)
    moved = geo.retract(poses, 1e-3 * rng.standard_normal((len(poses), geo.dof(g.dim))))
    d = g.dim
    R0 = poses[:, :d, :d].copy()
    R1 = R0 + 1e-3 * rng.standard_normal(R0.shape)
    none = [None] * len(links)
    pose_enc = [DeltaEncoder(absolute_every=TABLE1_DELTA_EVERY) for _ in links]
    rot_enc = [DeltaEncoder(absolute_every=TABLE1_DELTA_EVERY) for _ in links]
    _bytes(separators(1, poses), pose_enc)
    _bytes(rotations(1, R0), rot_enc)
    return {
        "links": len(links),
        "separator_copies": int(sum(len(n) for *_, n in links)),
        "absolute": _bytes(separators(1, poses), none),
        "delta": _bytes(separators(2, moved), pose_enc),
        "init_rot_delta": _bytes(rotations(2, R1), rot_enc),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", type=Path, help="folder with the six Table 1 g2o files")
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--only", nargs="+", choices=sorted(PAPER), help="some graphs only")
    args = ap.parse_args(argv)
    print(f"{'graph':<15} {'links':>5} {'copies':>6} {'absolute B':>10} {'delta B':>8} "
          f"{'init rot B':>10} {'bar MB':>7} {'bar / delta':>11}")
    for name in args.only or PAPER:
        file, bar_mb = PAPER[name][0], byte_bar_mb(name)
        path = args.data_dir / file
        if not path.exists():
            print(f"{name}: {path} not found", file=sys.stderr)
            return 2
        x = full_exchange_bytes(read_g2o(path), args.robots)
        print(f"{name:<15} {x['links']:>5} {x['separator_copies']:>6} {x['absolute']:>10} "
              f"{x['delta']:>8} {x['init_rot_delta']:>10} {bar_mb:>7} "
              f"{bar_mb * 1e6 / x['delta']:>11.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
