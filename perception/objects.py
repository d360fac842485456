"""Tags -> objects: T_body_object with a 6x6 covariance, fusing all tags of one box.

For an accepted tag k of object o (``T_object_tag`` from calib/tags.yaml):

    T_camera_object = T_camera_tag @ T_tag_object,  Sigma_o = Adj(T_object_tag) Sigma_k Adj(.)^T

(``covariance.transform_covariance``). When several tags of one object are accepted in the same
frame, the object pose is re-estimated from ALL their corners at once (Gauss-Newton on the
reprojection error of the corner points expressed in the object frame, started from the tag with
the smallest covariance), which also removes the planar ambiguity of each single tag; the joint
covariance is (J^T W J)^-1 over all 8k rows, W = diag(1 / sigma_tag^2), times the fit's
reduced chi-square when above 1 (``inflate_by_residual``). If the joint fit's RMS
error exceeds ``max_reproj_px`` (one tag is wrong), the best single tag is used.

Finally ``T_body_object = T_body_camera @ T_camera_object``; a fixed left factor leaves a
right-perturbation covariance unchanged. The extrinsic's own uncertainty is not added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from dran_edge.perception.covariance import gauss_newton, pose_covariance
from dran_edge.perception.tagpose import CORNER_TO_OPENCV_PX, TagPoses


@dataclass(frozen=True, eq=False)
class ObjectPoses:
    """Per observed object (m): id, pose in the body frame, covariance [t, r], tags used."""

    object_id: np.ndarray
    T_body_object: np.ndarray
    covariance: np.ndarray
    n_tags: np.ndarray


def fuse_objects(
    K: np.ndarray,
    T_body_camera: np.ndarray,
    corners: np.ndarray,
    tag_poses: TagPoses,
    map_pos: np.ndarray,
    object_id_of_pos: np.ndarray,
    T_tag_object: np.ndarray,
    adjoint_object_tag: np.ndarray,
    corners_object: np.ndarray,
    max_reproj_px: float,
    iterations: int = 2,
    inflate_by_residual: bool = True,
) -> ObjectPoses:
    """Objects seen in one frame from its accepted tags (``map_pos`` = tag-map position or -1).

    ``T_tag_object``, ``adjoint_object_tag`` = Adj(T_object_tag) and ``corners_object``
    (k, 4, 3), the tag corners in the object frame, are precomputed by ``calib.TagMap`` and
    indexed by tag-map position.
    """
    use = np.flatnonzero(tag_poses.accepted & (map_pos >= 0))
    if use.size == 0:
        return ObjectPoses(np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)),
                           np.zeros(0, np.int64))
    pos = map_pos[use]
    # group the (few) accepted tags by object in plain Python: cheaper than np.unique here
    groups: dict[int, list[int]] = {}
    for k, o in enumerate(object_id_of_pos[pos].tolist()):
        groups.setdefault(o, []).append(k)
    objects = sorted(groups)
    counts = np.array([len(groups[o]) for o in objects], np.int64)
    if counts.max() == 1:
        best = np.array([groups[o][0] for o in objects])
    else:
        # the tag with the smallest covariance trace represents (and starts) each object
        trace = np.trace(tag_poses.covariance[use], axis1=1, axis2=2).tolist()
        best = np.array([min(groups[o], key=trace.__getitem__) for o in objects])
    objects = np.array(objects, np.int64)
    pb = pos[best]
    T_out = tag_poses.T_camera_tag[use[best]] @ T_tag_object[pb]
    A = adjoint_object_tag[pb]  # = transform_covariance(cov, T_tag_object), precomputed
    cov_out = A @ tag_poses.covariance[use[best]] @ np.swapaxes(A, -1, -2)
    multi = np.flatnonzero(counts > 1)
    if multi.size:
        n_pts = 4 * counts[multi].max()
        P = np.zeros((multi.size, n_pts, 3))
        uv = np.zeros((multi.size, n_pts, 2))
        weight = np.zeros((multi.size, n_pts))
        for row, j in enumerate(multi):
            members = np.asarray(groups[int(objects[j])])
            k4 = 4 * members.size
            P[row, :k4] = corners_object[pos[members]].reshape(-1, 3)
            uv[row, :k4] = (corners[use[members]] + CORNER_TO_OPENCV_PX).reshape(-1, 2)
            weight[row, :k4] = np.repeat(1.0 / tag_poses.corner_sigma_px[use[members]], 4)
        # whitened least squares: residual / sigma per corner, so the covariance is (J^T J)^-1
        T_j, JtJ, r = gauss_newton(K, T_out[multi], P, uv, weight, iterations)
        valid = weight > 0
        r_px = r / np.where(valid, weight, 1.0)[..., None]
        rms = np.sqrt(np.sum(r_px * r_px, axis=(-1, -2)) / valid.sum(-1))
        ok = rms <= max_reproj_px
        T_out[multi[ok]] = T_j[ok]
        cov_joint = pose_covariance(JtJ[ok], 1.0)
        if inflate_by_residual:
            # Birge ratio of the joint fit: whitened residual sum of squares / (2N - 6)
            chi2 = np.sum(r[ok] * r[ok], axis=(-1, -2))
            dof = 2 * valid[ok].sum(-1) - 6
            cov_joint *= np.maximum(1.0, chi2 / dof)[:, None, None]
        cov_out[multi[ok]] = cov_joint
        counts = counts.copy()
        counts[multi[~ok]] = 1
    return ObjectPoses(objects.astype(np.int64), T_body_camera @ T_out, cov_out,
                       counts.astype(np.int64))
