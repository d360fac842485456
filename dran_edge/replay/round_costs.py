"""SR_cost per round: the costs of the merged graph as it stands at sampled rounds.

During a mission the merged graph (:mod:`dran_edge.replay.merged_g2o`) grows every round, so the
final F_init and F* of ``merged.g2o`` do not define an SR_cost for an earlier round. At every
``every``-th round (rounds k with (k + 1) divisible by ``every``) and at the last round, the
replay builds the merged graph of the robots' local graphs as they are after that round and
evaluates, with the SE-Sync objective and weights of the final SR_cost (docs/eval.md):

- ``F_k``: at the robots' current estimates (the graph's values, as merged.g2o's at the end);
- ``F_init``: at the robots' initial estimate (:func:`dran_edge.replay.outputs.initial_track`,
  what ``<robot>_init.tum`` holds) at the vertex stamps, each object placed by its first
  observation (:func:`dran_edge.evaluation.centralized.initial_objective`);
- ``F_star``: the centralized optimum of that graph (Schur-LM). The first sample starts from the
  chordal initialisation, like the final evaluation; later ones are warm-started from the
  previous sample's optimum (a vertex it did not have starts at the robots' estimate), which
  takes a few iterations. A warm start that ends above ``F_k`` (another basin) is solved again
  from the robots' estimate, so ``F_star ≤ F_k``.

SR_cost_k = (F_init − F_k)/(F_init − F*)·100 % (paper Sec. 6.2) and F_k/F* per sample. At the last
round the graph is merged.g2o's, so the values equal the evaluation's ``cost`` section to the
solver's tolerance (tests/test_round_costs.py). Written to report.json as ``round_costs`` and
``cost_init`` / ``cost_final`` / ``cost_centralized`` (docs/run-format.md).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge.errors import InputError
from dran_edge.evaluation import metrics
from dran_edge.evaluation.centralized import initial_objective, solve_centrally
from dran_edge.replay.merged_g2o import merged_graph
from dran_edge.replay.outputs import initial_track

if TYPE_CHECKING:
    from dran_edge.formats.g2o import G2oGraph
    from dran_edge.replay.robots import RobotResult
    from dran_edge.solver.centralized import SolveReport

log = logging.getLogger(__name__)

#: Default of ``--cost-every``: one sample per 20 rounds (10 s of mission at 2 Hz), which keeps
#: the demo's replay time within ~10 % (docs/replay.md).
COST_EVERY_DEFAULT = 20

#: Per-sample columns of report.json's ``round_costs`` (docs/run-format.md).
COLUMNS = (
    "round",
    "stamp_ns",
    "vertices",
    "edges",
    "F_init",
    "F_k",
    "F_star",
    "sr_cost_pct",
    "f_over_fstar",
    "centralized_iterations",
)

VertexKey = tuple[str, str, int]
"""(kind, robot or object name, stamp_ns) of a merged-graph vertex: stable across rounds, where
vertex ids are not (a robot's keyframe index shifts as its bounded graph drops nodes)."""


class RoundCosts:
    """The samples of one replay (see the module docstring); ``every`` 0 takes none."""

    def __init__(self, every: int, total_rounds: int) -> None:
        self.every = every
        self.total_rounds = total_rounds
        self.rows: list[dict[str, Any]] = []
        self.wall_s = 0.0
        self._optimum: dict[VertexKey, np.ndarray] = {}

    def due(self, k: int) -> bool:
        """Whether round ``k`` (0-based) is sampled."""
        return self.every > 0 and ((k + 1) % self.every == 0 or k == self.total_rounds - 1)

    def sample(self, k: int, stamp_ns: int, results: dict[int, RobotResult]) -> None:
        """The costs of the merged graph of ``results`` (the robots after round ``k``)."""
        t0 = time.perf_counter()
        merged = merged_graph(results)
        if merged is not None:
            self.rows.append(self._costs(k, stamp_ns, merged.graph, merged.vertex_map, results))
        self.wall_s += time.perf_counter() - t0

    def _costs(
        self,
        k: int,
        stamp_ns: int,
        g: G2oGraph,
        vmap: dict[int, VertexKey],
        results: dict[int, RobotResult],
    ) -> dict[str, Any]:
        from dran_edge.solver.objective import sesync_objective, sesync_weights

        kappa, tau = sesync_weights(g.dim, g.information)
        F_k = float(sesync_objective(g.poses, g.edges, g.measurements, kappa, tau))
        inits = {}
        for r in results.values():
            if r.last is not None and len(r.last.keyframe_stamps_ns):
                s_ns, T0, _ = initial_track(r)
                inits[r.name] = (np.asarray(s_ns, np.int64) * 1e-9, T0)
        F_init = initial_objective(g, vmap, inits)
        rep = self._solve(g, vmap, F_k)
        F_star = rep.objective_final if rep is not None else None
        return {
            "round": k,
            "stamp_ns": stamp_ns,
            "vertices": g.num_vertices,
            "edges": g.num_edges,
            "F_init": F_init,
            "F_k": F_k,
            "F_star": F_star,
            "sr_cost_pct": (
                float(metrics.sr_cost(F_init, F_k, F_star))
                if F_init is not None and F_star is not None
                else None
            ),
            "f_over_fstar": float(metrics.cost_ratio(F_k, F_star)) if F_star is not None else None,
            "centralized_iterations": int(rep.result.iterations) if rep is not None else None,
        }

    def _solve(self, g: G2oGraph, vmap: dict[int, VertexKey], F_k: float) -> SolveReport | None:
        """The centralized solve of ``g`` (warm-started, see the module docstring); None (and
        a warning) when the graph cannot be solved."""
        from dran_edge.solver.centralized import solve_g2o

        keys = [vmap[int(v)] for v in g.vertex_ids.tolist()]
        try:
            if not self._optimum:
                rep, _ = solve_centrally(g, [])
            else:
                T0 = g.poses.copy()
                for i, key in enumerate(keys):
                    if key in self._optimum and not g.fixed[i]:
                        T0[i] = self._optimum[key]
                rep = solve_g2o(dataclasses.replace(g, poses=T0), init="file")
            if not rep.objective_final <= F_k:
                again = solve_g2o(g, init="file")
                if again.objective_final < rep.objective_final:
                    rep = again
        except InputError as exc:
            log.warning("round costs: the merged graph was not solved (%s)", exc)
            return None
        self._optimum = dict(zip(keys, rep.result.poses))
        return rep

    def report(self) -> dict[str, Any]:
        """report.json's ``round_costs`` (columns) and the last sample's ``cost_init`` /
        ``cost_final`` / ``cost_centralized``; empty without samples."""
        if not self.rows:
            return {}
        last = self.rows[-1]
        out: dict[str, Any] = {
            "round_costs": {
                "every": self.every,
                "objective": "SE-Sync objective of the merged graph as of each round "
                "(objective.sesync_objective, the final SR_cost's)",
                **{c: [row[c] for row in self.rows] for c in COLUMNS},
            },
        }
        for key, col in (
            ("cost_init", "F_init"),
            ("cost_final", "F_k"),
            ("cost_centralized", "F_star"),
        ):
            if last[col] is not None and math.isfinite(last[col]):
                out[key] = last[col]
        return out
