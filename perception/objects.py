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
    # index bookkeeping in plain Python: a frame has a handful of tags, and a dozen numpy calls
    # on 1-3 element arrays would cost more than the maths below
    mp = map_pos.tolist()
    use_l = [i for i, ok in enumerate(tag_poses.accepted.tolist()) if ok and mp[i] >= 0]
    if not use_l:
        return ObjectPoses(
            np.zeros(0, np.int64), np.zeros((0, 4, 4)), np.zeros((0, 6, 6)), np.zeros(0, np.int64)
        )
    pos_l = [mp[i] for i in use_l]
    groups: dict[int, list[int]] = {}
    for k, o in enumerate(object_id_of_pos[pos_l].tolist()):
        groups.setdefault(o, []).append(k)
    object_list = sorted(groups)
    count_list = [len(groups[o]) for o in object_list]
    if max(count_list) == 1:
        best_l = [groups[o][0] for o in object_list]
    else:
        # the tag with the smallest covariance trace represents (and starts) each object
        trace = np.trace(tag_poses.covariance[use_l], axis1=1, axis2=2).tolist()
        best_l = [min(groups[o], key=trace.__getitem__) for o in object_list]
    sel = [use_l[k] for k in best_l]
    pb = [pos_l[k] for k in best_l]
    objects = np.array(object_list, np.int64)
    counts = np.array(count_list, np.int64)
    T_out = tag_poses.T_camera_tag[sel] @ T_tag_object[pb]
    A = adjoint_object_tag[pb]  # = transform_covariance(cov, T_tag_object), precomputed
    cov_out = A @ tag_poses.covariance[sel] @ A.transpose(0, 2, 1)
    if max(count_list) == 1:
        return ObjectPoses(objects, T_body_camera @ T_out, cov_out, counts)
    multi = [j for j, c in enumerate(count_list) if c > 1]
    n_pts = 4 * max(count_list)
    P = np.zeros((len(multi), n_pts, 3))
    uv = np.zeros((len(multi), n_pts, 2))
    weight = np.zeros((len(multi), n_pts))
    sigma = tag_poses.corner_sigma_px
    for row, j in enumerate(multi):
        members = groups[object_list[j]]
        m_use = [use_l[k] for k in members]
        k4 = 4 * len(members)
        P[row, :k4] = corners_object[[pos_l[k] for k in members]].reshape(-1, 3)
        uv[row, :k4] = corners[m_use].reshape(-1, 2) + CORNER_TO_OPENCV_PX
        weight[row, :k4] = np.repeat(1.0 / sigma[m_use], 4)
    # whitened least squares: residual / sigma per corner, so the covariance is (J^T J)^-1
    T_j, JtJ, r = gauss_newton(K, T_out[multi], P, uv, weight, iterations)
    valid = weight > 0
    n_valid = valid.sum(-1)
    r_px = r / np.where(valid, weight, 1.0)[..., None]
    rms = np.sqrt(np.sum(r_px * r_px, axis=(-1, -2)) / n_valid)
    cov_joint = pose_covariance(JtJ, 1.0)
    if inflate_by_residual:
        # Birge ratio of the joint fit: whitened residual sum of squares / (2N - 6)
        chi2 = np.sum(r * r, axis=(-1, -2))
        cov_joint *= np.maximum(1.0, chi2 / (2 * n_valid - 6))[:, None, None]
    for row, j in enumerate(multi):
        if rms[row] <= max_reproj_px:
            T_out[j] = T_j[row]
            cov_out[j] = cov_joint[row]
        else:  # one of its tags is wrong: keep the best single tag
            counts[j] = 1
    return ObjectPoses(objects, T_body_camera @ T_out, cov_out, counts)
