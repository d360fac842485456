"""Tag poses from the four detected corners: both planar solutions, ambiguity, rejection.

A square seen by a pinhole camera has two poses that fit the corners almost equally well when the
tag is small, far or seen nearly head-on (the planar ambiguity; Schweighofer & Pinz, PAMI 2006;
Collins & Bartoli, "Infinitesimal Plane-based Pose Estimation", IJCV 2014). We:

1. reject detections before any maths: hamming distance, decision margin, shortest edge in
   pixels, corners too close to the image border (the library extrapolates truncated tags; their
   corners are off by pixels);
2. get BOTH IPPE solutions from ``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` and refine each
   with two Gauss-Newton steps on the reprojection error (``covariance.gauss_newton``), all tags
   at once;
3. choose the lower reprojection error; the tag is *ambiguous* when ``rms_alt / rms_best`` is
   below ``ambiguity_ratio``. With aligned depth, an ambiguous tag takes the solution whose
   predicted depth on a 4x4 grid inside the tag matches the measured depth better (median
   absolute residual), when that preference is larger than the depth noise. Still-ambiguous
   tags whose two solutions differ by less than ``ambiguity_merge_angle_rad`` are kept with the
   covariance widened by the spread; others are rejected (a wrong pose is worse than none);
4. reject by range and by the RMS reprojection error of the chosen solution.

Pixel convention: detector corners have pixel centres at half-integers; OpenCV's ``K`` at integers,
so ``uv = corners + CORNER_TO_OPENCV_PX`` (measured: +0.50 px offset, std 0.07 px, in
tests/test_perception_detector.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import ConfigError
from dran_edge.perception.covariance import gauss_newton, pose_covariance
from dran_edge.perception.detector import TagDetections

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
    """Standard deviation of one corner coordinate, pixels (the covariance scale; calibrate with
    ``dran-edge detect --json`` summary's ``corner_sigma_px`` on your camera)."""
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
    refine_iterations: int = 2
    """Gauss-Newton steps on the reprojection error after IPPE."""

    def __post_init__(self) -> None:
        for name in ("min_edge_px", "max_range_m", "max_reproj_px", "corner_sigma_px",
                     "ambiguity_ratio", "depth_max_residual_m"):
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
    JtJ: np.ndarray
    reject: np.ndarray
    method: np.ndarray

    @property
    def accepted(self) -> np.ndarray:
        return self.reject == OK


def tag_object_points(size_m: np.ndarray) -> np.ndarray:
    """Tag-frame corners ``(n, 4, 3)`` in the detector's order for sizes ``(n,)`` in metres."""
    return UNIT_CORNERS[None] * (np.asarray(size_m, dtype=np.float64)[:, None, None] / 2)


def _ippe_both(uv: np.ndarray, size_m: float, K: np.ndarray) -> np.ndarray:
    """Both IPPE_SQUARE solutions ``(2, 4, 4)`` (the second repeats the first if only one)."""
    import cv2

    obj = UNIT_CORNERS * (size_m / 2)
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, uv, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    out = np.tile(np.eye(4), (2, 1, 1))
    for k in range(2):
        j = min(k, n - 1)
        out[k, :3, :3] = cv2.Rodrigues(rvecs[j])[0]
        out[k, :3, 3] = tvecs[j].ravel()
    return out


def _depth_residual(T: np.ndarray, size_m: np.ndarray, K: np.ndarray, depth_mm: np.ndarray):
    """Median |measured - predicted| depth (m) and valid count, per pose ``T (n, 2, 4, 4)``."""
    h, w = depth_mm.shape
    pts = np.zeros((T.shape[0], 1, _DEPTH_GRID.shape[0], 3))
    pts[..., :2] = _DEPTH_GRID * (size_m[:, None, None, None] / 2)
    p = np.einsum("...ij,...nj->...ni", T[..., :3, :3], pts) + T[..., None, :3, 3]
    z = p[..., 2]
    u = np.rint(K[0, 0] * p[..., 0] / z + K[0, 2]).astype(np.int64)
    v = np.rint(K[1, 1] * p[..., 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (z > 0)
    meas = depth_mm[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)].astype(np.float64) * 1e-3
    valid = inside & (meas > 0)
    res = np.where(valid, np.abs(meas - z), np.nan)
    count = valid.sum(-1)
    with np.errstate(all="ignore"):
        med = np.nanmedian(np.where(count[..., None] > 0, res, 0.0), axis=-1)
    return np.where(count > 0, med, np.inf), count


def estimate_tag_poses(
    det: TagDetections,
    K: np.ndarray,
    tag_size_m: np.ndarray,
    image_size: tuple[int, int],
    depth_mm: np.ndarray | None = None,
    params: TagPoseParams | None = None,
    known: np.ndarray | None = None,
) -> TagPoses:
    """Poses of the detections ``det`` (``tag_size_m (n,)`` per detection; NaN = unknown size).

    ``image_size`` is ``(width, height)``; ``depth_mm`` an aligned uint16 depth image or None;
    ``known (n,)`` marks tags present in the tag map (others get ``REJECT_UNKNOWN`` and no pose).
    """
    p = params or TagPoseParams()
    n = len(det)
    K = np.asarray(K, dtype=np.float64)
    size = np.asarray(tag_size_m, dtype=np.float64).reshape(n)
    nan44 = np.full((n, 4, 4), np.nan)
    T_best, T_alt = nan44.copy(), nan44.copy()
    cov = np.full((n, 6, 6), np.nan)
    JtJ_best = np.full((n, 6, 6), np.nan)
    rms = np.full(n, np.nan)
    rms_alt = np.full(n, np.nan)
    reject = np.full(n, OK, dtype=object)
    method = np.full(n, "", dtype=object)
    if n == 0:
        return TagPoses(T_best, cov, T_alt, rms, rms_alt, JtJ_best, reject, method)

    uv = det.corners + CORNER_TO_OPENCV_PX
    edge = np.linalg.norm(np.roll(uv, -1, axis=1) - uv, axis=-1).min(-1)
    w, h = image_size
    b = p.border_px
    inside = np.all((uv[..., 0] >= b - 0.5) & (uv[..., 0] <= w - 0.5 - b)
                    & (uv[..., 1] >= b - 0.5) & (uv[..., 1] <= h - 0.5 - b), axis=-1)
    known = np.isfinite(size) if known is None else (np.asarray(known, bool) & np.isfinite(size))
    # first failing rule wins
    for bad, why in ((~known, REJECT_UNKNOWN), (det.hamming > p.max_hamming, REJECT_HAMMING),
                     (det.decision_margin < p.min_decision_margin, REJECT_MARGIN),
                     (edge < p.min_edge_px, REJECT_SMALL), (~inside, REJECT_BORDER)):
        reject[(reject == OK) & bad] = why
    idx = np.flatnonzero(reject == OK)
    if idx.size == 0:
        return TagPoses(T_best, cov, T_alt, rms, rms_alt, JtJ_best, reject, method)

    m = idx.size
    T0 = np.stack([_ippe_both(uv[i], size[i], K) for i in idx])  # (m, 2, 4, 4)
    P = np.repeat(tag_object_points(size[idx])[:, None], 2, axis=1)  # (m, 2, 4, 3)
    obs = np.repeat(uv[idx][:, None], 2, axis=1)
    T2, JtJ2, r2 = gauss_newton(K, T0, P, obs, iterations=p.refine_iterations)
    rms2 = np.sqrt(np.mean(np.sum(r2 * r2, -1), -1))  # (m, 2)
    order = np.argsort(rms2, axis=1)  # index 0 = lower reprojection error
    pick = order[:, 0]
    method_m = np.full(m, "reprojection", dtype=object)
    reject_m = np.full(m, OK, dtype=object)

    ar = np.arange(m)
    rb0, ra0 = rms2[ar, pick], rms2[ar, 1 - pick]
    floor = p.corner_sigma_px / 2
    ambiguous = np.maximum(ra0, floor) / np.maximum(rb0, floor) < p.ambiguity_ratio
    if depth_mm is not None:
        dres, dcount = _depth_residual(T2, size[idx], K, depth_mm)
        enough = np.all(dcount >= p.depth_min_points, axis=1)
        # depth decides an ambiguous tag only when its preference exceeds its own noise:
        # the median of n samples of |N(0, s)| has a spread of about 1.25 s / sqrt(n).
        z = np.abs(T2[:, 0, 2, 3])
        noise = 3 * 1.25 * p.depth_sigma_coeff_per_m * z * z / np.sqrt(np.maximum(dcount.min(1), 1))
        gap = np.abs(dres[:, 0] - dres[:, 1])
        use = ambiguous & enough & (gap > np.maximum(noise, p.depth_decisive_m))
        pick = np.where(use, np.argmin(dres, axis=1), pick)
        method_m[use] = "depth"
        ambiguous = ambiguous & ~use
        chosen_res = dres[ar, pick]
        reject_m[enough & (chosen_res > p.depth_max_residual_m)] = REJECT_DEPTH

    Tb, Ta = T2[ar, pick], T2[ar, 1 - pick]
    rb, ra = rms2[ar, pick], rms2[ar, 1 - pick]
    cov_m = pose_covariance(JtJ2[ar, pick], p.corner_sigma_px)
    if np.any(ambiguous):
        d = geo.se3_log(geo.se3_between(Tb, Ta))  # (m, 6)
        angle = np.linalg.norm(d[:, 3:], axis=-1)
        merge = ambiguous & (angle < p.ambiguity_merge_angle_rad)
        cov_m = cov_m + merge[:, None, None] * (d[:, :, None] * d[:, None, :])
        reject_m[ambiguous & ~merge & (reject_m == OK)] = REJECT_AMBIGUOUS
    too_far = np.linalg.norm(Tb[:, :3, 3], axis=-1) > p.max_range_m
    reject_m[(reject_m == OK) & too_far] = REJECT_RANGE
    reject_m[(reject_m == OK) & ~(rb <= p.max_reproj_px)] = REJECT_REPROJ

    T_best[idx], T_alt[idx], cov[idx] = Tb, Ta, cov_m
    JtJ_best[idx] = JtJ2[ar, pick]
    rms[idx], rms_alt[idx] = rb, ra
    reject[idx], method[idx] = reject_m, method_m
    return TagPoses(T_best, cov, T_alt, rms, rms_alt, JtJ_best, reject, method)
