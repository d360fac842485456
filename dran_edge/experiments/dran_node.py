"""A DRAN agent as a node of ``comms.loopback``: the same robot code in one process per robot.

``comms.loopback`` runs one node per robot either all in one process over the in-process bus
(``run_bus_fleet``) or as separate processes over real RADIO/DISH sockets on loopback
(``run_loopback_fleet``), both through the authenticated ``NeighbourLink``. This node wraps
one :class:`dran_edge.dran.agent.Agent` on its part of an object simulation
(``objects_sim.make_scenario``), so the two runs of the same problem can be compared.

Node config (JSON): ``sim`` (``SimParams`` fields), ``edges`` (the fleet's communication graph,
for the Metropolis–Hastings weights, which need the neighbours' degrees) and ``agent``
(``AgentConfig`` overrides).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from dran_edge.dran.agent import Agent
from dran_edge.config import AgentConfig
from dran_edge.dran.consensus import metropolis_hastings_matrix
from dran_edge.events import NeighbourData, Outgoing, Tick
from dran_edge.messages import NeighbourMessage
from dran_edge.experiments.fleet import ROUND_PERIOD_NS
from dran_edge.experiments.objects import SimParams, make_scenario


class DranNode:
    """Robot ``robot_id`` of the simulated scenario, driven round by round."""

    def __init__(self, robot_id: int, neighbours: list[int], config: dict):
        sim_kw: dict[str, Any] = {
            k: tuple(v) if isinstance(v, list) else v for k, v in config.get("sim", {}).items()
        }
        sim = SimParams(**sim_kw)
        scenario = make_scenario(sim)
        n = sim.num_robots
        A = np.zeros((n, n), dtype=bool)
        for a, b in config["edges"]:
            A[a, b] = A[b, a] = True
        W = metropolis_hastings_matrix(A)
        cfg = dataclasses.replace(
            AgentConfig(**config.get("agent", {})),
            robot_id=robot_id,
            neighbours=tuple(sorted(neighbours)),
        )
        self.agent = Agent(
            cfg, scenario.problems[robot_id], {q: float(W[robot_id, q]) for q in neighbours}
        )

    def step(
        self, round_: int, received: list[NeighbourMessage]
    ) -> list[tuple[NeighbourMessage, list[int]]]:
        stamp_ns = round_ * ROUND_PERIOD_NS
        for message in received:
            self.agent.handle(NeighbourData(stamp_ns, message))
        return [
            (o.message, list(o.to))
            for o in self.agent.handle(Tick(stamp_ns))
            if isinstance(o, Outgoing)
        ]

    def result(self) -> dict:
        """The estimate, exactly (floats as hex so JSON round-trips every bit)."""
        return {
            "rounds": self.agent.k,
            "trajectory": [float(v).hex() for v in np.asarray(self.agent.x).ravel()],
            "objects": {
                str(o): [float(v).hex() for v in T.ravel()] for o, T in sorted(self.agent.y.items())
            },
        }
