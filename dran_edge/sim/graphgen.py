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
    pt_list: list[tuple[float, float, float]] = []
    yaw_list: list[float] = []
    for layer in range(layers if dim == 3 else 1):
        for row in range(side):
            cols = range(side) if row % 2 == 0 else range(side - 1, -1, -1)
            for col in cols:
                pt_list.append((col * step_m, row * step_m, layer * step_m))
                yaw_list.append(0.0 if row % 2 == 0 else np.pi)
    pts, yaw = np.asarray(pt_list), np.asarray(yaw_list)
    if dim == 2:
        return geo.se2_from_xy_theta(np.column_stack([pts[:, :2], yaw]))
    rng = np.random.default_rng(12345)
    tilt = rng.normal(scale=0.05, size=(yaw.size, 2))  # small roll/pitch so 3D is really 3D
    R = geo.so3_exp(np.column_stack([tilt, yaw]))
    return geo.se3_from_rt(R, pts)


def _generated_graph(
    dim: int, poses: np.ndarray, edges: np.ndarray, Z: np.ndarray, information: np.ndarray
) -> G2oGraph:
    """A G2oGraph of generated data: vertex ids 0..n-1, every vertex posed, none fixed, one
    information matrix per edge (``(m, r, r)``; broadcast from ``(r, r)``)."""
    n, m, r = poses.shape[0], edges.shape[0], 3 if dim == 2 else 6
    return G2oGraph(
        dim=dim,
        vertex_ids=np.arange(n, dtype=np.int64),
        poses=poses,
        has_pose=np.ones(n, dtype=bool),
        edges=edges,
        measurements=Z,
        information=np.broadcast_to(information, (m, r, r)).copy(),
        fixed=np.zeros(n, dtype=bool),
        edge_lines=np.arange(1, m + 1, dtype=np.int64),
    )


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
    return _generated_graph(dim, T.copy(), edges, Z, info), T


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
    """A long noisy 2D trajectory on a street grid (:func:`road_trajectory`, one pose per metre)
    with loop closures.

    Odometry links consecutive poses; about ``loop_fraction``·n loop closures link a pose to a
    random earlier pose (at least ``min_gap`` poses back) within ``loop_radius_m``. Noise as in
    :func:`synthetic_graph`, the loop closures' ``loop_noise_scale`` times larger than their
    information says (scan matches that are worse than they claim, as in real data). The
    vertices of the returned graph are the odometry composition of the noisy measurements (the
    dead reckoning a file would hold), not the truth; returns (graph, true poses).
    """
    from scipy.spatial import cKDTree

    T = road_trajectory(2, num_poses, seed, step_m=1.0, block_m=block_m, blocks=blocks)
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
    dead = np.empty_like(T)
    dead[0] = T[0]
    for k in range(n - 1):
        dead[k + 1] = dead[k] @ Z[k]
    return _generated_graph(2, dead, edges, Z, np.diag(1.0 / sig**2)), T


# --------------------------------------------------------------------------- suite families
# Generators for the generalisation suite (docs/notes/generalisation.md): long odometry chains
# with sparse loops (car / long indoor), dense grid worlds, noisy and anisotropic variants.


def road_trajectory(
    dim: int,
    num_poses: int,
    seed: int,
    step_m: float = 1.0,
    block_m: float = 20.0,
    blocks: int = 8,
    hills_m: float = 0.0,
) -> np.ndarray:
    """(n, D, D) true poses of a vehicle driving a grid of streets: ``blocks`` × ``blocks``
    city blocks of ``block_m`` metres, one pose every ``step_m``; at each intersection it goes
    straight, left or right at random (never back, never off the map), so it revisits streets
    at random, as a car or a robot in long corridors does. In 3D the streets follow smooth
    hills of amplitude ``hills_m`` (pitch from the slope) with a small random roll."""
    rng = np.random.default_rng(seed)
    per_block = max(1, int(round(block_m / step_m)))
    size = blocks * per_block
    heading = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
    cell, h = np.array([0, 0]), 0
    cells, headings = [], []
    for _ in range(num_poses):
        cells.append(cell.copy())
        headings.append(h)
        if np.all(cell % per_block == 0):  # intersection: choose among allowed directions
            options = [
                k
                for k in ((h + 1) % 4, h, (h + 3) % 4)
                if np.all((cell + heading[k] >= 0) & (cell + heading[k] <= size))
            ]
            h = int(rng.choice(options)) if options else (h + 2) % 4
        cell = cell + heading[h]
        headings[-1] = h  # the pose faces where it drives next
    xy = np.asarray(cells, dtype=np.float64) * step_m
    yaw = np.asarray(headings) * (np.pi / 2)
    if dim == 2:
        return geo.se2_from_xy_theta(np.column_stack([xy, yaw]))
    L = size * step_m + 1.0
    z = hills_m * np.sin(2 * np.pi * xy[:, 0] / L) * np.cos(2 * np.pi * xy[:, 1] / L)
    dz = np.gradient(z) / step_m if z.size > 1 else np.zeros_like(z)
    pitch = -np.arctan(dz)
    roll = rng.normal(scale=0.02, size=z.size)
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.stack(
        [
            np.stack([c, -s, 0 * c], -1),
            np.stack([s, c, 0 * c], -1),
            np.stack([0 * c, 0 * c, 1 + 0 * c], -1),
        ],
        1,
    )
    R = Rz @ geo.so3_exp(np.column_stack([roll, pitch, np.zeros_like(roll)]))
    return geo.se3_from_rt(R, np.column_stack([xy, z]))


def grid_walk_trajectory(
    dim: int, num_poses: int, seed: int, side: int = 30, turn_probability: float = 0.3
) -> np.ndarray:
    """(n, D, D) true poses of a random walk on a ``side`` × ``side`` unit grid (3D: also up
    and down between layers), turning with ``turn_probability`` at every node: the "city"
    worlds of M3500 / city10000 (Olson et al. 2006), dense with revisits."""
    rng = np.random.default_rng(seed)
    dirs = [
        np.array(v) for v in ((1, 0, 0), (0, 1, 0), (-1, 0, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))
    ]
    ndir = 6 if dim == 3 else 4
    layers = max(2, side // 6) if dim == 3 else 1
    lim = np.array([side - 1, side - 1, layers - 1])
    p, h = np.zeros(3, dtype=np.int64), 0
    pt_list: list[np.ndarray] = []
    hs: list[int] = []
    for _ in range(num_poses):
        if rng.random() < turn_probability or np.any((p + dirs[h] < 0) | (p + dirs[h] > lim)):
            back = (h + 2) % 4 if h < 4 else 9 - h
            ok = [
                k
                for k in range(ndir)
                if np.all((p + dirs[k] >= 0) & (p + dirs[k] <= lim)) and k != back
            ]
            h = int(rng.choice(ok))
        p = p + dirs[h]
        pt_list.append(p.copy())
        hs.append(h)
    pts = np.asarray(pt_list, dtype=np.float64)
    yaw = np.array([(k if k < 4 else 0) * np.pi / 2 for k in hs])
    if dim == 2:
        return geo.se2_from_xy_theta(np.column_stack([pts[:, :2], yaw]))
    tilt = rng.normal(scale=0.05, size=(yaw.size, 2))
    return geo.se3_from_rt(geo.so3_exp(np.column_stack([tilt, yaw])), pts)


def loop_pairs(
    T: np.ndarray, radius_m: float, min_gap: int, count: int | None, seed: int
) -> np.ndarray:
    """(k, 2) loop closures i < j − ``min_gap`` between poses within ``radius_m``; ``count``
    of them drawn uniformly at random (spread over the trajectory), or all when None."""
    from scipy.spatial import cKDTree

    d = T.shape[-1] - 1
    pairs = cKDTree(T[:, :d, d]).query_pairs(radius_m, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros((0, 2), np.int64)
    pairs = np.sort(pairs, axis=1)
    pairs = pairs[pairs[:, 1] - pairs[:, 0] > min_gap]
    pairs = pairs[np.lexsort((pairs[:, 0], pairs[:, 1]))]
    if count is not None and count < len(pairs):
        rng = np.random.default_rng(seed + 7919)
        pairs = pairs[np.sort(rng.choice(len(pairs), size=count, replace=False))]
    return pairs.astype(np.int64)


def graph_from_trajectory(
    T: np.ndarray, loops: np.ndarray, sigma_t_m, sigma_r_rad, seed: int, anisotropy: float = 1.0
) -> G2oGraph:
    """A pose graph over true poses ``T``: odometry between consecutive poses plus ``loops``,
    measurements perturbed on the right by ``Exp(n)``, n ~ N(0, Σ). ``sigma_t_m`` /
    ``sigma_r_rad`` are scalars or per-axis arrays. ``anisotropy`` > 1 draws, per edge, a
    random rotation of the translation covariance with axis standard deviations spread
    by that ratio (correlated, non-diagonal information); 1 keeps it diagonal. The vertices
    hold the true poses (the suite starts from its own initialisation)."""
    dim = T.shape[-1] - 1
    n = T.shape[0]
    dof = 6 if dim == 3 else 3
    edges = np.concatenate([np.column_stack([np.arange(n - 1), np.arange(1, n)]), loops])
    edges = edges.astype(np.int64)
    m = edges.shape[0]
    Z = geo.between(T[edges[:, 0]], T[edges[:, 1]])
    rng = np.random.default_rng(seed)
    st = np.broadcast_to(np.asarray(sigma_t_m, float), (dim,))
    sr = np.broadcast_to(np.asarray(sigma_r_rad, float), (dof - dim,))
    cov = np.zeros((m, dof, dof))
    cov[:, :dim, :dim] = np.diag(st**2)
    cov[:, dim:, dim:] = np.diag(sr**2)
    if anisotropy != 1.0:
        scales = np.geomspace(1.0, anisotropy, dim) / np.sqrt(anisotropy)
        if dim == 2:
            Q = geo.so2_exp(np.asarray(rng.uniform(-np.pi, np.pi, m)))
        else:
            Q = geo.so3_exp(rng.normal(size=(m, 3)) * 2.0)
        cov[:, :dim, :dim] = Q @ np.diag((st * scales) ** 2) @ np.swapaxes(Q, 1, 2)
    Lc = np.linalg.cholesky(cov)
    noise = (Lc @ rng.normal(size=(m, dof, 1)))[..., 0]
    Z = geo.retract(Z, noise)
    info = np.linalg.inv(cov)
    info = 0.5 * (info + np.swapaxes(info, 1, 2))
    return _generated_graph(dim, T.copy(), edges, Z, info)
