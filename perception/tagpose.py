"""Tag poses from the four detected corners: both planar solutions, ambiguity, rejection.

A square seen by a pinhole camera has two poses that fit the corners almost equally well when the
tag is small, far or seen nearly head-on (the planar ambiguity; Schweighofer & Pinz, PAMI 2006;
Collins & Bartoli, "Infinitesimal Plane-based Pose Estimation", IJCV 2014). We:

1. reject detections before any maths: unknown tag, hamming distance, decision margin, shortest
   edge in pixels, corners too close to the image border (the library extrapolates truncated
   tags; their corners are off by pixels);
2. get BOTH IPPE solutions from ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` with their
   reprojection errors; optionally refine the chosen one with Gauss-Newton
   (``refine_iterations``; ``covariance.gauss_newton``, all tags at once) and linearise it for
   the covariance (``covariance.py``);
3. choose the lower reprojection error; the tag is *ambiguous* when ``rms_alt / rms_best`` is
   below ``ambiguity_ratio``. With aligned depth, an ambiguous tag takes the solution whose
   predicted depth on a 4x4 grid inside the tag matches the measured depth better (median
   absolute residual), when that preference is larger than the depth noise. Still-ambiguous
   tags whose two solutions differ by less than ``ambiguity_merge_angle_rad`` are kept with the
   covariance widened by the spread; others are rejected (a wrong pose is worse than none);
4. reject by range and by the RMS reprojection error of the chosen solution.

Everything per frame is vectorised over tags except the OpenCV call per tag and the rejection
screen, which runs in plain Python because a frame holds a handful of tags.

Pixel convention: detector corners have pixel centres at half-integers; OpenCV's ``K`` at integers,
so ``uv = corners + CORNER_TO_OPENCV_PX`` (measured: +0.50 px offset, std 0.07 px, in
tests/test_perception_detector.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from dran_edge.perception.covariance import gauss_newton, linearise, pose_covariance
from dran_edge.perception.detector import TagDetections

from dran_edge import geometry as geo
from dran_edge.errors import ConfigError

CORNER_TO_OPENCV_PX = -0.5

# Reasons a detection is not turned into an observation (``TagPoses.reject``).
OK = ""
REJECT_HAMMING = "hamming"
REJECT_MARGIN = "decision_margin"
REJECT_SMALL = "min_edge_px"
REJECT_BORDER = "border"
REJECT_RANGE = "max_range"
REJECT_REPROJ = "reprojection"
REJECT_AMBIGUOUS = "ambiguous"
REJECT_DEPTH = "depth_mismatch"
REJECT_UNKNOWN = "unknown_tag"

# Tag-frame corners in the detector's order, for a tag of size 2 (scale by size / 2).
UNIT_CORNERS = np.array([[-1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, -1.0, 0.0], [-1.0, -1.0, 0.0]])
_g = np.linspace(-0.75, 0.75, 4)
_DEPTH_GRID = np.stack(np.meshgrid(_g, _g), -1).reshape(-1, 2)  # 16 points, units of size/2


@dataclass(frozen=True)
class TagPoseParams:
    """Rejection, ambiguity and noise parameters of tag pose estimation."""

    max_hamming: int = 1
    """Largest accepted number of corrected bits (tag36h11 corrects up to 2; 2 admits more
    false positives)."""
    min_decision_margin: float = 25.0
    """Smallest accepted decision margin (grey levels of contrast at the decoded bits)."""
    min_edge_px: float = 12.0
    """Shortest edge of the tag's quad in pixels; smaller tags are rejected."""
    border_px: float = 2.0
    """All corners must lie at least this far inside the image (truncated tags are rejected)."""
    max_range_m: float = 6.0
    """Largest accepted distance from the camera centre to the tag centre, metres."""
    max_reproj_px: float = 1.5
    """Largest accepted RMS reprojection error of the chosen solution, pixels."""
    corner_sigma_px: float = 0.3
    """Standard deviation of one corner coordinate, pixels, for a tag whose shortest edge is
    ``corner_sigma_ref_edge_px``; a tag with shortest edge L gets sigma * sqrt(ref / L) (edges are
    line fits over L pixels). The covariance scale: calibrate with the ``corner_sigma_px`` of
    ``dran-edge detect``'s summary on your camera."""
    corner_sigma_ref_edge_px: float = 50.0
    """Reference shortest-edge length in pixels for ``corner_sigma_px``."""
    inflate_by_residual: bool = True
    """Multiply a pose's covariance by its reduced chi-square (the Birge ratio: residual sum of
    squares / (sigma^2 dof), dof = 2 per tag) when that exceeds 1, so poorly fitting tags
    (blur, noise, partial occlusion) are not over-confident."""
    ambiguity_ratio: float = 1.5
    """Without depth: the tag is ambiguous when rms(alternative) / rms(best) is below this
    (both RMS floored at ``corner_sigma_px / 2``)."""
    ambiguity_merge_angle_rad: float = np.deg2rad(10.0)
    """Ambiguous tags whose two solutions differ by less than this rotation are kept, with the
    covariance widened by the spread; others are rejected."""
    depth_min_points: int = 6
    """Fewest valid depth samples (of 16 inside the tag) needed to use depth for the choice."""
    depth_sigma_coeff_per_m: float = 0.003
    """Depth noise model sigma_z = coeff * z^2 (metres), used to judge whether depth is decisive."""
    depth_decisive_m: float = 0.003
    """Depth decides only when the two solutions' median depth residuals differ by more than this
    (and by more than 3x the noise of the medians)."""
    depth_max_residual_m: float = 0.10
    """Reject when the chosen solution's median depth residual exceeds this (misaligned depth)."""
    refine_iterations: int = 0
    """Gauss-Newton steps on the reprojection error after IPPE (IPPE is already within a few
    hundredths of a pixel of the least-squares pose for four points; see the tests)."""

    def __post_init__(self) -> None:
        for name in (
            "min_edge_px",
            "max_range_m",
            "max_reproj_px",
            "corner_sigma_px",
            "ambiguity_ratio",
            "depth_max_residual_m",
        ):
            if not float(getattr(self, name)) > 0:
                raise ConfigError(f"tag pose {name}: expected > 0, got {getattr(self, name)!r}")
        if self.max_hamming not in (0, 1, 2):
            raise ConfigError(f"tag pose max_hamming: expected 0, 1 or 2, got {self.max_hamming!r}")


@dataclass(frozen=True, eq=False)
class TagPoses:
    """Per detection (n): chosen pose and covariance, the alternative, and the verdict.

    ``T_camera_tag (n, 4, 4)`` and ``covariance (n, 6, 6)`` (right perturbation, [t, r]) are
    NaN where the pose was not computed; ``reject`` holds ``""`` for accepted tags or a reason.
    ``method`` is ``"depth"``, ``"reprojection"`` or ``""``.
    """

    T_camera_tag: np.ndarray
    covariance: np.ndarray
    T_camera_tag_alt: np.ndarray
    rms_px: np.ndarray
    rms_alt_px: np.ndarray
    reject: np.ndarray
    method: np.ndarray
    accepted: np.ndarray
    """Boolean ``(n,)``: ``reject == ""``."""
    corner_sigma_px: np.ndarray
    """Corner noise used for each tag's covariance ``(n,)`` (NaN where not computed)."""
    min_edge_px: np.ndarray
    """Shortest edge of each tag's quad in pixels ``(n,)``."""


def corner_sigma(p: TagPoseParams, min_edge_px: np.ndarray) -> np.ndarray:
    """Corner noise per tag: ``corner_sigma_px * sqrt(ref_edge / shortest edge)`` (pixels)."""
    return p.corner_sigma_px * np.sqrt(
        p.corner_sigma_ref_edge_px / np.maximum(np.asarray(min_edge_px, dtype=float), 1.0)
    )


def tag_object_points(size_m: np.ndarray) -> np.ndarray:
    """Tag-frame corners ``(n, 4, 3)`` in the detector's order for sizes ``(n,)`` in metres."""
    return UNIT_CORNERS[None] * (np.asarray(size_m, dtype=np.float64)[:, None, None] / 2)


def _depth_residual(T: np.ndarray, size_m: np.ndarray, K: np.ndarray, depth_mm: np.ndarray):
    """Median |measured - predicted| depth (m) and valid count, per pose ``T (n, 2, 4, 4)``."""
    h, w = depth_mm.shape
    pts = np.zeros((T.shape[0], 1, _DEPTH_GRID.shape[0], 3))
    pts[..., :2] = _DEPTH_GRID * (size_m[:, None, None, None] / 2)
    p = geo.se3_transform_points(T, pts)
    z = p[..., 2]
    u = np.rint(K[0, 0] * p[..., 0] / z + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * p[..., 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (z > 0)
    meas = depth_mm[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)] * 1e-3
    valid = inside & (meas > 0)
    res = np.sort(np.where(valid, np.abs(meas - z), np.inf), axis=-1)
    count = valid.sum(-1)
    lo = np.take_along_axis(res, np.maximum((count - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(res, np.maximum(count // 2, 0)[..., None], -1)[..., 0]
    return np.where(count > 0, 0.5 * (lo + hi), np.inf), count


def _screen(
    corners: list, hamming: list, margin: list, size: list, w: int, h: int, p: TagPoseParams
) -> tuple[list[str], list[float]]:
    """Rejection before any pose maths, per tag in plain Python (a frame has a few tags; this
    is several times cheaper than a dozen numpy calls on 4x2 arrays)."""
    out, edges = [], []
    lo_x = lo_y = p.border_px - 0.5
    hi_x, hi_y = w - 1 - lo_x, h - 1 - lo_y
    min_edge_sq = p.min_edge_px**2
    for c, ham, dm, s in zip(corners, hamming, margin, size):
        edge_sq = min((c[k][0] - c[k - 1][0]) ** 2 + (c[k][1] - c[k - 1][1]) ** 2 for k in range(4))
        edges.append(edge_sq**0.5)
        if not s == s:  # NaN size: not in the tag map
            out.append(REJECT_UNKNOWN)
        elif ham > p.max_hamming:
            out.append(REJECT_HAMMING)
        elif dm < p.min_decision_margin:
            out.append(REJECT_MARGIN)
        elif edge_sq < min_edge_sq:
            out.append(REJECT_SMALL)
        elif not all(lo_x <= x <= hi_x and lo_y <= y <= hi_y for x, y in c):
            out.append(REJECT_BORDER)
        else:
            out.append(OK)
    return out, edges


def estimate_tag_poses(
    det: TagDetections,
    K: np.ndarray,
    tag_size_m: np.ndarray,
    image_size: tuple[int, int],
    depth_mm: np.ndarray | None = None,
    params: TagPoseParams | None = None,
) -> TagPoses:
    """Poses of the detections ``det``; ``tag_size_m (n,)`` per detection, NaN for tags without a
    known size (rejected as ``unknown_tag``). ``image_size`` is ``(width, height)``; ``depth_mm``
    an aligned uint16 depth image in millimetres, or None."""
    # Long: the per-tag pipeline (PnP, ambiguity, depth, covariance) in the order of docs/perception.md.
    p = params or TagPoseParams()
    n = len(det)
    size = np.asarray(tag_size_m, dtype=np.float64).reshape(n)
    T_both = np.full((n, 2, 4, 4), np.nan)  # [chosen, alternative]
    cov = np.full((n, 6, 6), np.nan)
    rms_both = np.full((n, 2), np.nan)
    sigma = np.full(n, np.nan)
    method = [""] * n
    if n == 0:
        return TagPoses(
            T_both[:, 0],
            cov,
            T_both[:, 1],
            rms_both[:, 0],
            rms_both[:, 1],
            np.array([], dtype=object),
            np.array([], dtype=object),
            np.zeros(0, bool),
            sigma,
            np.zeros(0),
        )
    uv = det.corners + CORNER_TO_OPENCV_PX
    reject, edges = _screen(
        uv.tolist(),
        det.hamming.tolist(),
        det.decision_margin.tolist(),
        size.tolist(),
        image_size[0],
        image_size[1],
        p,
    )
    idx = [i for i, r in enumerate(reject) if r == OK]
    m = len(idx)

    def result() -> TagPoses:
        return TagPoses(
            T_both[:, 0],
            cov,
            T_both[:, 1],
            rms_both[:, 0],
            rms_both[:, 1],
            np.array(reject, dtype=object),
            np.array(method, dtype=object),
            np.array([r == OK for r in reject]),
            sigma,
            np.asarray(edges),
        )

    if m == 0:
        return result()

    K = np.asarray(K, dtype=np.float64)
    idx_a = np.asarray(idx)
    T2, rms2 = _ippe_solutions(K, uv[idx_a], size[idx_a])
    floor = p.corner_sigma_px / 2
    ambiguous = [max(a, floor) / max(b, floor) < p.ambiguity_ratio for b, a in rms2.tolist()]
    method_m = ["reprojection"] * m
    reject_m = [OK] * m
    if depth_mm is not None and any(ambiguous):
        _decide_by_depth(T2, rms2, size[idx_a], K, depth_mm, p, ambiguous, method_m, reject_m)
    Tb = T2[:, 0]
    P = UNIT_CORNERS * (size[idx_a, None, None] / 2)
    if p.refine_iterations:
        Tb, JtJ, res = gauss_newton(K, Tb, P, uv[idx_a], iterations=p.refine_iterations)
        T2[:, 0] = Tb
        rms2[:, 0] = np.sqrt(np.mean(np.sum(res * res, axis=-1), axis=-1))
    else:
        J = linearise(K, Tb, P)[1].reshape(m, 8, 6)
        JtJ = np.swapaxes(J, 1, 2) @ J
    sigma_m = corner_sigma(p, [edges[i] for i in idx])
    cov_m = pose_covariance(JtJ, sigma_m)
    if p.inflate_by_residual:
        # 4 corners: sum r^2 = 4 rms^2 over 8 - 6 = 2 degrees of freedom
        birge = np.maximum(1.0, 2.0 * rms2[:, 0] ** 2 / sigma_m**2)
        cov_m *= birge[:, None, None]
    _merge_or_reject_ambiguous(Tb, T2[:, 1], cov_m, p, ambiguous, reject_m)
    _check_range_and_reprojection(Tb, rms2[:, 0], p, reject_m)
    T_both[idx_a] = T2
    rms_both[idx_a] = rms2
    cov[idx_a] = cov_m
    sigma[idx_a] = sigma_m
    for row, i in enumerate(idx):
        reject[i] = reject_m[row]
        method[i] = method_m[row]
    return result()


def _ippe_solutions(K: np.ndarray, uv: np.ndarray, size: np.ndarray):
    """Both IPPE solutions per tag, lower reprojection error first: ``(T (m, 2, 4, 4), rms (m,
    2))``. OpenCV reports the RMS per coordinate, ours is per corner (x sqrt 2). One solution
    only -> repeated."""
    import cv2

    m = size.shape[0]
    T2 = np.zeros((m, 2, 4, 4))
    T2[..., 3, 3] = 1.0
    rms2 = np.empty((m, 2))
    for row in range(m):
        k_sol, rvecs, tvecs, e = cv2.solvePnPGeneric(
            UNIT_CORNERS * (size[row] / 2), uv[row], K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        order = (0, 0) if k_sol < 2 else ((0, 1) if e[0, 0] <= e[1, 0] else (1, 0))
        for k, j in enumerate(order):
            T2[row, k, :3, :3] = cv2.Rodrigues(rvecs[j])[0]
            T2[row, k, :3, 3] = tvecs[j][:, 0]
            rms2[row, k] = e[j, 0] * 1.4142135623730951
    return T2, rms2


def _decide_by_depth(
    T2, rms2, size, K, depth_mm, p: TagPoseParams, ambiguous: list, method_m: list, reject_m: list
) -> None:
    """Depth is consulted only for ambiguous tags (the others are decided by reprojection); it
    decides only when its preference exceeds its own noise: the median of n samples of
    |N(0, s)| has a spread of about 1.25 s / sqrt(n). Swaps ``T2``/``rms2`` rows in place."""
    amb = np.flatnonzero(ambiguous)
    dres, dcount = _depth_residual(T2[amb], size[amb], K, depth_mm)
    enough = np.all(dcount >= p.depth_min_points, axis=1)
    z = np.abs(T2[amb, 0, 2, 3])
    noise = 3 * 1.25 * p.depth_sigma_coeff_per_m * z * z / np.sqrt(np.maximum(dcount.min(1), 1))
    gap = np.abs(dres[:, 0] - dres[:, 1])
    use = enough & (gap > np.maximum(noise, p.depth_decisive_m))
    choice = np.argmin(dres, axis=1)
    swap = [False] * len(ambiguous)
    for a, row in enumerate(amb.tolist()):
        if use[a]:
            swap[row] = bool(choice[a] == 1)
            method_m[row] = "depth"
            ambiguous[row] = False
            if dres[a, choice[a]] > p.depth_max_residual_m:
                reject_m[row] = REJECT_DEPTH
    if any(swap):
        flip = np.asarray(swap)
        T2[flip] = T2[flip][:, ::-1]
        rms2[flip] = rms2[flip][:, ::-1]


def _merge_or_reject_ambiguous(
    Tb, T_alt, cov_m, p: TagPoseParams, ambiguous: list, reject_m: list
) -> None:
    """An ambiguous tag whose two solutions are close keeps the best with their difference
    added to its covariance; one whose solutions are far apart is rejected."""
    if not any(ambiguous):
        return
    d = geo.se3_log(geo.se3_between(Tb, T_alt))  # (m, 6)
    angle = np.linalg.norm(d[:, 3:], axis=-1)
    for row, amb in enumerate(ambiguous):
        if amb:
            if angle[row] < p.ambiguity_merge_angle_rad:
                cov_m[row] += np.outer(d[row], d[row])
            elif reject_m[row] == OK:
                reject_m[row] = REJECT_AMBIGUOUS


def _check_range_and_reprojection(Tb, rms, p: TagPoseParams, reject_m: list) -> None:
    max_range_sq = p.max_range_m**2
    rb = rms.tolist()
    for row, (x, y, z_) in enumerate(Tb[:, :3, 3].tolist()):
        if reject_m[row] == OK:
            if x * x + y * y + z_ * z_ > max_range_sq:
                reject_m[row] = REJECT_RANGE
            elif not rb[row] <= p.max_reproj_px:
                reject_m[row] = REJECT_REPROJ
