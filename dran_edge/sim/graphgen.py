"""Synthetic pose graphs with known ground truth, for tests, the demo and quick benchmarks.

A robot drives a square grid "lawn-mower" path (3D: several stacked layers, like a garage);
odometry links consecutive poses and loop closures link poses whose positions are within
``loop_radius_m``. Measurements are the true relative poses perturbed on the right by
``Exp(n)``, ``n ~ N(0, diag(σ_t² I, σ_r² I))``; information is the inverse of that covariance.
"""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo
from dran_edge.formats.g2o import G2oGraph


def grid_trajectory(dim: int, side: int, layers: int = 1, step_m: float = 1.0) -> np.ndarray:
    """(n, D, D) true poses along a boustrophedon path over a side×side grid (× layers in 3D)."""
    pts, yaw = [], []
    for layer in range(layers if dim == 3 else 1):
        for row in range(side):
            cols = range(side) if row % 2 == 0 else range(side - 1, -1, -1)
            for col in cols:
                pts.append((col * step_m, row * step_m, layer * step_m))
                yaw.append(0.0 if row % 2 == 0 else np.pi)
    pts, yaw = np.asarray(pts), np.asarray(yaw)
    if dim == 2:
        return geo.se2_from_xy_theta(np.column_stack([pts[:, :2], yaw]))
    rng = np.random.default_rng(12345)
    tilt = rng.normal(scale=0.05, size=(yaw.size, 2))  # small roll/pitch so 3D is really 3D
    R = geo.so3_exp(np.column_stack([tilt, yaw]))
    return geo.se3_from_rt(R, pts)


def synthetic_graph(
    dim: int = 3,
    side: int = 6,
    layers: int = 2,
    loop_radius_m: float = 1.1,
    sigma_t_m: float = 0.02,
    sigma_r_rad: float = 0.01,
    seed: int = 0,
) -> tuple[G2oGraph, np.ndarray]:
    """(graph with the true poses as vertices, true poses). σ = 0 gives noiseless measurements
    (with a unit information matrix)."""
    T = grid_trajectory(dim, side, layers)
    n = T.shape[0]
    odo = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    pos = T[:, :dim, dim]
    dist = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    ii, jj = np.nonzero((dist <= loop_radius_m) & (np.arange(n)[None] > np.arange(n)[:, None] + 1))
    edges = np.concatenate([odo, np.column_stack([ii, jj])]).astype(np.int64)
    Z = geo.between(T[edges[:, 0]], T[edges[:, 1]])
    dof = 6 if dim == 3 else 3
    sig = np.array([sigma_t_m] * dim + [sigma_r_rad] * (dof - dim))
    rng = np.random.default_rng(seed)
    if np.any(sig > 0):
        Z = geo.retract(Z, rng.normal(size=(edges.shape[0], dof)) * sig)
        info = np.diag(1.0 / sig**2)
    else:
        info = np.eye(dof)
    m = edges.shape[0]
    graph = G2oGraph(
        dim=dim,
        vertex_ids=np.arange(n, dtype=np.int64),
        poses=T.copy(),
        has_pose=np.ones(n, dtype=bool),
        edges=edges,
        measurements=Z,
        information=np.broadcast_to(info, (m, dof, dof)).copy(),
        fixed=np.zeros(n, dtype=bool),
        edge_lines=np.arange(1, m + 1, dtype=np.int64),
    )
    return graph, T
