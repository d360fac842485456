"""What the benchmarks in tools/bench/ share: the paper's six g2o graphs, where they live, and the
small generated graphs that stand in for them under ``--quick``.

A script imports it as ``import _common`` (Python puts the script's own folder first on the
module path). Importing it sets one BLAS thread unless the caller chose otherwise, so import it
before numpy (docs/benchmarks.md, conditions).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
#: Where the g2o graphs are unless a script is given a data directory.
DEFAULT_G2O_DIR = REPO.parent / "shared" / "data" / "g2o"

#: The paper's Table 1 graphs: name -> (file in the data directory, F*). F* is the SE-Sync
#: objective at the centralized optimum (exact LM, ‖grad‖ ≤ 2e-4; docs/benchmarks.md).
G2O_GRAPHS: dict[str, tuple[str, float]] = {
    "parking-garage": ("parking-garage.g2o", 1.26252443),
    "sphere2500": ("sphere2500.g2o", 1687.00581),
    "torus3D": ("torus3D.g2o", 24227.0456),
    "CSAIL": ("CSAIL.g2o", 31.4703317),
    "intel": ("input_INTEL_g2o.g2o", 393.652541),
    "manhattan": ("input_M3500_g2o.g2o", 193.862258),
}


def default_g2o_dir() -> str | None:
    """The shared data directory if it exists (a script's default DATA_DIR), else None."""
    return str(DEFAULT_G2O_DIR) if DEFAULT_G2O_DIR.exists() else None


def quick_g2o_graphs(out_dir: str | Path) -> dict[str, tuple[str, float]]:
    """Two small generated graphs (SE(2) and SE(3), ``dran_edge.sim.graphgen``) written as g2o
    files into ``out_dir``: name -> (file, F*), F* from our centralized solver (chordal residual,
    exact Hessian, to 1e-10). For ``--quick`` runs, which check that a script works, not its
    numbers; the same keys as :data:`G2O_GRAPHS` so a script can use either."""
    from dran_edge.formats.g2o import read_g2o, write_g2o
    from dran_edge.sim.graphgen import synthetic_graph
    from dran_edge.solver.centralized import initial_poses, pose_graph
    from dran_edge.solver.lm import LMParams, solve
    from dran_edge.solver.objective import sesync_objective, sesync_weights

    out: dict[str, tuple[str, float]] = {}
    specs = {
        "quick-se2": {"dim": 2, "side": 6, "layers": 1, "loop_radius_m": 1.5},
        "quick-se3": {"dim": 3, "side": 4, "layers": 2, "loop_radius_m": 1.1},
    }
    for name, spec in specs.items():
        graph, _ = synthetic_graph(sigma_t_m=0.05, sigma_r_rad=0.02, seed=1, **spec)
        path = Path(out_dir) / f"{name}.g2o"
        write_g2o(path, graph)
        g = read_g2o(path)  # what the script will read: the file's rounding included
        res = solve(
            pose_graph(g, "chordal", "sesync"),
            initial_poses(g, "chordal"),
            LMParams(cost_tol=1e-10, hessian="exact"),
        )
        kappa, tau = sesync_weights(g.dim, g.information)
        out[name] = (
            path.name,
            float(sesync_objective(res.poses, g.edges, g.measurements, kappa, tau)),
        )
    return out
