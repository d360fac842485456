"""Chordal initialisation of SE(2)/SE(3) pose graphs (Carlone et al., ICRA 2015; the recipe of
SE-Sync/dpgo that the paper's Sec. 4.2.1 distributes).

1. Rotations: relax R_i ∈ SO(d) to R_i ∈ R^{d×d} and solve the linear least squares
   ``min Σ κ_ij ‖R_j − R_i R̃_ij‖²_F`` with the anchor's rotation fixed to I. Row a of
   ``R_j − R_i R̃_ij`` is ``r_j^a − r_i^a R̃_ij``, so the d rows decouple and share one sparse
   normal matrix (d unknowns per pose, d right-hand sides). Each R_i is then projected to SO(d).
2. Translations: with the rotations fixed, ``min Σ τ_ij ‖t_j − t_i − R_i t̃_ij‖²`` with the anchor
   at the origin; the coordinates decouple into a weighted graph Laplacian with d right-hand sides.

The anchor (gauge) pose is the identity; compose with the wanted anchor pose afterwards.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge import geometry as geo
from dran_edge.errors import InputError


def _solve_spd(L: sp.spmatrix, rhs: np.ndarray) -> np.ndarray:
    lu = spla.splu(
        sp.csc_matrix(L),
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    x: np.ndarray = lu.solve(rhs)
    return x


def _check_connected(n: int, edges: np.ndarray) -> None:
    adj = sp.coo_matrix((np.ones(edges.shape[0]), (edges[:, 0], edges[:, 1])), shape=(n, n))
    count, labels = sp.csgraph.connected_components(adj, directed=False)
    if count > 1:
        raise InputError(
            f"the pose graph has {count} connected components, expected 1 "
            f"(vertex positions {np.flatnonzero(labels != labels[0])[:5].tolist()} … are not "
            "connected to the first); chordal initialisation needs a connected graph"
        )


def relaxed_rotation_system(
    n: int, edges: np.ndarray, R_meas: np.ndarray, kappa: np.ndarray, anchor: int = 0
) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """Normal equations ``A X = B`` of the relaxed rotation least squares (stage 1 above) over
    the unknowns ``X_v = R_vᵀ`` stacked per vertex (d rows each), the anchor's rotation fixed to
    I: returns ``(A, B, free)`` with ``free`` the (n·d,) mask of the rows that are unknowns."""
    d = R_meas.shape[-1]
    m = edges.shape[0]
    i, j = edges[:, 0], edges[:, 1]
    w = np.sqrt(np.asarray(kappa, dtype=np.float64))
    # Rows (e, b): (r_j)_b − Σ_c (R̃ᵀ)_{bc} (r_i)_c, weighted by √κ_e.
    eb = (np.arange(m)[:, None] * d + np.arange(d)[None]).ravel()
    rows_plus = eb
    cols_plus = (j[:, None] * d + np.arange(d)[None]).ravel()
    vals_plus = np.repeat(w, d)
    rows_minus = np.repeat(eb, d)
    cols_minus = (i[:, None, None] * d + np.arange(d)[None, None, :]).repeat(d, axis=1).ravel()
    vals_minus = (-np.swapaxes(R_meas, 1, 2) * w[:, None, None]).ravel()
    J = sp.csr_matrix(
        (
            np.concatenate([vals_plus, vals_minus]),
            (np.concatenate([rows_plus, rows_minus]), np.concatenate([cols_plus, cols_minus])),
        ),
        shape=(m * d, n * d),
    )
    free = np.ones(n * d, dtype=bool)
    free[anchor * d : (anchor + 1) * d] = False
    J_free, J_fix = J[:, free], J[:, ~free]
    # anchor rotation I: column a of the fixed unknowns is e_a, so J_fix @ I gives each RHS.
    return sp.csr_matrix(J_free.T @ J_free), -(J_free.T @ (J_fix @ np.eye(d))), free


def relaxed_to_rotations(X_free: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(n, d, d) rotations: the relaxed unknowns (anchor rows I) projected to SO(d)."""
    d = X_free.shape[1]
    X = np.zeros((free.size, d))
    X[free] = X_free
    X[~free] = np.eye(d)
    R = np.swapaxes(X.reshape(-1, d, d), 1, 2)  # R_i[a, b] = X[i·d + b, a]
    return geo.so3_project(R)


def chordal_rotations(
    n: int, edges: np.ndarray, R_meas: np.ndarray, kappa: np.ndarray, anchor: int = 0
) -> np.ndarray:
    """(n, d, d) rotations from the relaxed κ-weighted least squares, projected to SO(d)."""
    A, B, free = relaxed_rotation_system(n, edges, R_meas, kappa, anchor)
    return relaxed_to_rotations(_solve_spd(A, B), free)


def chordal_translations(
    n: int, edges: np.ndarray, R: np.ndarray, t_meas: np.ndarray, tau: np.ndarray, anchor: int = 0
) -> np.ndarray:
    """(n, d) translations minimising Σ τ ‖t_j − t_i − R_i t̃‖² for fixed rotations, t_anchor = 0."""
    m = edges.shape[0]
    i, j = edges[:, 0], edges[:, 1]
    Dm = sp.csr_matrix(
        (
            np.concatenate([np.ones(m), -np.ones(m)]),
            (np.concatenate([np.arange(m), np.arange(m)]), np.concatenate([j, i])),
        ),
        shape=(m, n),
    )
    b = (R[i] @ t_meas[:, :, None])[:, :, 0]
    Wd = sp.diags(np.asarray(tau, dtype=np.float64))
    free = np.ones(n, dtype=bool)
    free[anchor] = False
    D_free = Dm[:, free]
    t = np.zeros((n, R.shape[-1]))
    t[free] = _solve_spd(D_free.T @ Wd @ D_free, D_free.T @ (Wd @ b))
    return t


def chordal_initialization(
    n: int,
    edges: np.ndarray,
    measurements: np.ndarray,
    kappa: np.ndarray,
    tau: np.ndarray,
    anchor: int = 0,
) -> np.ndarray:
    """(n, D, D) poses from the two-stage chordal initialisation, the anchor at the identity.

    Raises InputError when the graph is not connected.
    """
    edges = np.asarray(edges, dtype=np.int64)
    measurements = np.asarray(measurements, dtype=np.float64)
    d = measurements.shape[-1] - 1
    _check_connected(n, edges)
    R = chordal_rotations(n, edges, measurements[:, :d, :d], kappa, anchor)
    t = chordal_translations(n, edges, R, measurements[:, :d, d], tau, anchor)
    T = np.zeros((n, d + 1, d + 1))
    T[:, :d, :d] = R
    T[:, :d, d] = t
    T[:, d, d] = 1.0
    return T
