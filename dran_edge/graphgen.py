"""Synthetic pose graphs with known ground truth, for tests, the demo and quick benchmarks.

A robot drives a square grid "lawn-mower" path (3D: several stacked layers, like a garage);
odometry links consecutive poses and loop closures link poses whose positions are within
``loop_radius_m``. Measurements are the true relative poses perturbed on the right by
``Exp(n)``, ``n ~ N(0, diag(σ_t² I, σ_r² I))``; information is the inverse of that covariance.
"""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo
from dran_edge.g2o import G2oGraph


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


def city_trajectory(
    num_poses: int, block_m: float = 10.0, blocks: int = 12, step_m: float = 1.0, seed: int = 0
) -> np.ndarray:
    """(n, 3, 3) true SE(2) poses of a robot driving a long random route on a city street grid.

    The streets are the lines x = k·block_m and y = k·block_m of a ``blocks``×``blocks`` grid; the
    robot advances ``step_m`` per pose and picks a random street (never a U-turn unless at the
    border) at every intersection, so it revisits the same streets many times, as a car or a
    long indoor dataset does.
    """
    rng = np.random.default_rng(seed)
    steps = int(round(block_m / step_m))
    heading = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
    cell, d = np.array([0, 0]), 0
    xy, yaw = [], []
    while len(xy) < num_poses:
        options = []
        for nd in ((d + 1) % 4, d, (d + 3) % 4):
            nxt = cell + heading[nd]
            if np.all((nxt >= 0) & (nxt <= blocks)):
                options.append(nd)
        d = int(rng.choice(options)) if options else (d + 2) % 4
        start = cell * block_m
        for s in range(steps):
            xy.append(start + heading[d] * s * step_m)
            yaw.append(np.arctan2(heading[d][1], heading[d][0]))
        cell = cell + heading[d]
    xy, yaw = np.asarray(xy[:num_poses], float), np.asarray(yaw[:num_poses])
    return geo.se2_from_xy_theta(np.column_stack([xy, yaw]))


def city_graph(
    num_poses: int = 15000,
    loop_fraction: float = 0.1,
    loop_radius_m: float = 0.6,
    min_gap: int = 30,
    sigma_t_m: float = 0.05,
    sigma_r_rad: float = 0.02,
    loop_noise_scale: float = 1.0,
    block_m: float = 10.0,
    blocks: int = 12,
    seed: int = 0,
) -> tuple[G2oGraph, np.ndarray]:
    """A long noisy 2D trajectory on a street grid (:func:`city_trajectory`) with loop closures.

    Odometry links consecutive poses; about ``loop_fraction``·n loop closures link a pose to a
    random earlier pose (at least ``min_gap`` poses back) within ``loop_radius_m``. Noise as in
    :func:`synthetic_graph`, the loop closures' ``loop_noise_scale`` times larger than their
    information says (scan matches that are worse than they claim, as in real data). The
    vertices of the returned graph are the odometry composition of the noisy measurements (the
    dead reckoning a file would hold), not the truth; returns (graph, true poses).
    """
    from scipy.spatial import cKDTree

    T = city_trajectory(num_poses, block_m, blocks, seed=seed)
    n = T.shape[0]
    rng = np.random.default_rng(seed + 1)
    pos = T[:, :2, 2]
    pairs = cKDTree(pos).query_pairs(loop_radius_m, output_type="ndarray")
    pairs = pairs[np.abs(pairs[:, 1] - pairs[:, 0]) >= min_gap]
    want = min(int(round(loop_fraction * n)), pairs.shape[0])
    loops = np.sort(pairs[rng.choice(pairs.shape[0], size=want, replace=False)], axis=1)
    odo = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    edges = np.concatenate([odo, loops]).astype(np.int64)
    Z = geo.between(T[edges[:, 0]], T[edges[:, 1]])
    sig = np.array([sigma_t_m, sigma_t_m, sigma_r_rad])
    scale = np.where(np.arange(edges.shape[0]) < n - 1, 1.0, loop_noise_scale)
    Z = geo.retract(Z, rng.normal(size=(edges.shape[0], 3)) * sig * scale[:, None])
    m = edges.shape[0]
    dead = np.empty_like(T)
    dead[0] = T[0]
    for k in range(n - 1):
        dead[k + 1] = dead[k] @ Z[k]
    graph = G2oGraph(
        dim=2,
        vertex_ids=np.arange(n, dtype=np.int64),
        poses=dead,
        has_pose=np.ones(n, dtype=bool),
        edges=edges,
        measurements=Z,
        information=np.broadcast_to(np.diag(1.0 / sig**2), (m, 3, 3)).copy(),
        fixed=np.zeros(n, dtype=bool),
        edge_lines=np.arange(1, m + 1, dtype=np.int64),
    )
    return graph, T
