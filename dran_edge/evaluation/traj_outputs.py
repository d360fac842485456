"""What ``dran-edge eval traj`` writes besides its printout: an evo-style results file and a plot.

The results file is the zip ``evo_ape --save_results`` writes and ``evo_res`` reads
(evo.tools.file_interface.save_res_file): ``info.json`` (title, ref_name, est_name, label),
``stats.json`` (rmse, mean, median, std, min, max, sse of the translation error, m),
``error_array.npy``, ``timestamps.npy``, ``seconds_from_start.npy`` and the matched reference
and aligned estimate as ``<name>.tum``. Written with the standard library and numpy: evo is not
needed to write it. The plot needs matplotlib (the ``eval`` extra).
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import DependencyError
from dran_edge.evaluation.traj_score import TrajectoryEvaluation

_ALIGN_TITLE = {
    "se3": "\n(with SE(3) Umeyama alignment)",
    "sim3": "\n(with Sim(3) Umeyama alignment)",
    "yaw": "\n(with yaw + translation alignment)",
    "none": "\n(not aligned)",
    "paper": "\n(aligned at the first pose)",
}


def _errors(res: TrajectoryEvaluation) -> np.ndarray:
    return np.linalg.norm(res.T_est_aligned[:, :3, 3] - res.T_ref[:, :3, 3], axis=1)


def _tum_text(stamps_s: np.ndarray, T: np.ndarray) -> str:
    rows = geo.se3_to_tum_rows(stamps_s, T)
    buf = io.StringIO()
    np.savetxt(buf, rows, fmt=["%.9f"] + ["%.10f"] * 7)
    return buf.getvalue()


def write_evo_results(
    path: str | Path, res: TrajectoryEvaluation, est_name: str, ref_name: str
) -> Path:
    """The evo results zip of one ``evaluate_trajectory`` result (APE, translation part)."""
    e = _errors(res)
    ref_name = ref_name if ref_name != est_name else ref_name + "_ref"
    info = {
        "title": "APE w.r.t. translation part (m)"
        + _ALIGN_TITLE.get(res.result["align"]["kind"], ""),
        "ref_name": ref_name,
        "est_name": est_name,
        "label": "APE (m)",
    }
    stats = {
        "rmse": float(np.sqrt(np.mean(e * e))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "sse": float(np.sum(e * e)),
    }
    arrays = {
        "error_array": e,
        "timestamps": res.stamps_s,
        "seconds_from_start": res.stamps_s - res.stamps_s[0],
    }
    path = Path(path)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("info.json", json.dumps(info))
        z.writestr("stats.json", json.dumps(stats))
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.save(buf, np.asarray(a, dtype=np.float64))
            z.writestr(f"{name}.npy", buf.getvalue())
        z.writestr(f"{ref_name}.tum", _tum_text(res.stamps_s, res.T_ref))
        z.writestr(f"{est_name}.tum", _tum_text(res.stamps_s, res.T_est_aligned))
    return path


def plot_trajectory(
    path: str | Path, res: TrajectoryEvaluation, est_name: str, ref_name: str
) -> Path:
    """Top view (x-y) of the aligned estimate and the reference, and the error over time."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise DependencyError("--plot needs matplotlib: pip install 'dran-edge[eval]'") from None
    e = _errors(res)
    r = res.result
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    a.plot(res.T_ref[:, 0, 3], res.T_ref[:, 1, 3], "k--", lw=1, label=ref_name)
    a.plot(res.T_est_aligned[:, 0, 3], res.T_est_aligned[:, 1, 3], lw=1.2, label=est_name)
    a.set_xlabel("x (m)")
    a.set_ylabel("y (m)")
    a.set_aspect("equal", adjustable="datalim")
    a.legend(loc="best", fontsize=8)
    a.set_title(f"top view, {r['align']['kind']} alignment")
    t = res.stamps_s - res.stamps_s[0]
    b.plot(t, e, lw=1)
    b.axhline(r["ate_rmse_m"], color="r", ls=":", label=f"RMSE {r['ate_rmse_m']:.4f} m")
    b.set_xlabel("time since the first matched pose (s)")
    b.set_ylabel("translation error (m)")
    b.set_title("APE, translation part")
    b.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
