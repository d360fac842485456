"""Tag poses: accuracy, the planar ambiguity with and without depth, rejection rules."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pupil_apriltags")
pytest.importorskip("cv2")

from dran_edge.perception.detector import TagDetections, TagDetector, to_gray  # noqa: E402
from dran_edge.perception.render import DepthModel, TagRenderer  # noqa: E402
from dran_edge.perception.tagpose import (  # noqa: E402
    REJECT_BORDER,
    REJECT_HAMMING,
    REJECT_MARGIN,
    REJECT_RANGE,
    REJECT_REPROJ,
    REJECT_SMALL,
    REJECT_UNKNOWN,
    TagPoseParams,
    estimate_tag_poses,
)

from dran_edge import geometry as geo  # noqa: E402

K = np.array([[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]])


def rot_deg(yaw: float, pitch: float, roll: float) -> np.ndarray:
    y, p, r = np.deg2rad([yaw, pitch, roll])
    return (
        geo.so3_exp(np.array([0, y, 0]))
        @ geo.so3_exp(np.array([p, 0, 0]))
        @ geo.so3_exp(np.array([0, 0, r]))
    )


def errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    d = geo.se3_log(geo.se3_between(T_est, T_true))
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(
        np.rad2deg(np.linalg.norm(d[3:]))
    )


@pytest.fixture(scope="module")
def tools():
    return TagRenderer(), TagDetector()


def test_16cm_tag_at_1m_no_blur(tools):
    """Must-reach: position error <= 1 cm and rotation error <= 1 deg."""
    renderer, det = tools
    rng = np.random.default_rng(11)
    worst_t = worst_r = 0.0
    n = 0
    for yaw in (-40, -20, 0, 20, 40):
        for pitch in (-15, 15):
            T = geo.se3_from_rt(
                rot_deg(yaw, pitch, rng.uniform(-180, 180)),
                [rng.uniform(-0.2, 0.2), rng.uniform(-0.1, 0.1), 1.0],
            )
            colour, depth = renderer.render(K, 640, 480, [T], [4], 0.16, rng=rng)
            tp = estimate_tag_poses(det.detect(to_gray(colour)), K, [0.16], (640, 480), depth)
            assert tp.accepted.tolist() == [True]
            e_t, e_r = errors(tp.T_camera_tag[0], T)
            worst_t, worst_r = max(worst_t, e_t), max(worst_r, e_r)
            n += 1
    assert n == 10
    assert worst_t <= 0.01, worst_t
    assert worst_r <= 1.0, worst_r


def sweep(renderer, det, use_depth: bool):
    """Viewing-angle sweep -> (accepted, flips, rejected); a flip = rotation error > 10 deg."""
    rng = np.random.default_rng(21)
    accepted = flips = rejected = 0
    for dist in (1.0, 2.0, 3.0):
        for pitch in (-20.0, 0.0, 20.0):
            for yaw in np.arange(-70.0, 71.0, 5.0):
                T = geo.se3_from_rt(
                    rot_deg(yaw, pitch, rng.uniform(-180, 180)),
                    [rng.uniform(-0.1, 0.1) * dist, 0.0, dist],
                )
                colour, depth = renderer.render(
                    K,
                    640,
                    480,
                    [T],
                    [9],
                    0.16,
                    noise_sigma=3.0,
                    blur_sigma_px=0.6,
                    rng=rng,
                    depth=DepthModel(coeff_per_m=0.002),
                )
                d = det.detect(to_gray(colour))
                if len(d) != 1:
                    continue
                tp = estimate_tag_poses(d, K, [0.16], (640, 480), depth if use_depth else None)
                if not tp.accepted[0]:
                    rejected += 1
                    continue
                accepted += 1
                flips += errors(tp.T_camera_tag[0], T)[1] > 10.0
    return accepted, flips, rejected


def test_ambiguity_sweep_without_depth(tools):
    accepted, flips, rejected = sweep(*tools, use_depth=False)
    assert accepted > 200
    assert flips <= 0.01 * accepted, (flips, accepted)
    assert rejected <= 0.15 * (accepted + rejected)


def test_ambiguity_sweep_with_depth_has_no_flips(tools):
    accepted, flips, rejected = sweep(*tools, use_depth=True)
    assert accepted > 200
    assert flips == 0


def test_both_solutions_kept_and_sorted(tools):
    renderer, det = tools
    T = geo.se3_from_rt(rot_deg(25, 10, 170), [0.05, 0.0, 2.5])
    colour, _ = renderer.render(K, 640, 480, [T], [2], 0.16)
    tp = estimate_tag_poses(det.detect(to_gray(colour)), K, [0.16], (640, 480))
    assert np.all(np.isfinite(tp.T_camera_tag_alt[0]))
    assert tp.rms_px[0] <= tp.rms_alt_px[0]
    # the alternative is the mirror solution: a different rotation, a similar range
    _, e_r = errors(tp.T_camera_tag_alt[0], tp.T_camera_tag[0])
    assert e_r > 1.0
    assert abs(tp.T_camera_tag_alt[0, 2, 3] - tp.T_camera_tag[0, 2, 3]) < 0.05


def fake(corners, hamming=0, margin=100.0):
    c = np.asarray(corners, float)[None]
    return TagDetections(np.array([1]), np.array([hamming]), np.array([margin]), c)


SQUARE = [[300.5, 280.5], [380.5, 280.5], [380.5, 200.5], [300.5, 200.5]]


def _tilted() -> np.ndarray:
    """Exact corners (detector convention) of a 16 cm tag at 1 m turned 50 deg (unambiguous)."""
    T = geo.se3_from_rt(rot_deg(50, 10, 180), [0.0, 0.0, 1.0])
    s = 0.08 * np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]])
    p = (s @ T[:3, :3].T + T[:3, 3]) @ K.T
    return p[:, :2] / p[:, 2:] + 0.5


TILTED = _tilted()


@pytest.mark.parametrize(
    ("det", "size", "params", "why"),
    [
        (fake(SQUARE, hamming=2), 0.16, TagPoseParams(max_hamming=1), REJECT_HAMMING),
        (fake(SQUARE, margin=5.0), 0.16, TagPoseParams(), REJECT_MARGIN),
        (fake(np.asarray(SQUARE) * 0.1), 0.16, TagPoseParams(), REJECT_SMALL),
        (fake(np.asarray(SQUARE) - [300, 0]), 0.16, TagPoseParams(), REJECT_BORDER),
        (fake(SQUARE), np.nan, TagPoseParams(), REJECT_UNKNOWN),
        (fake(SQUARE), 0.16, TagPoseParams(max_range_m=0.5), REJECT_RANGE),
        (
            fake(TILTED + [[0, 0], [0, 0], [2.0, -2.0], [0, 0]]),
            0.16,
            TagPoseParams(max_reproj_px=0.3),
            REJECT_REPROJ,
        ),
    ],
)
def test_rejection_rules(det, size, params, why):
    tp = estimate_tag_poses(det, K, [size], (640, 480), params=params)
    assert tp.reject.tolist() == [why]
    assert not tp.accepted[0]


def test_exact_tilted_corners_give_the_pose():
    tp = estimate_tag_poses(fake(TILTED), K, [0.16], (640, 480))
    assert tp.accepted.tolist() == [True] and tp.method.tolist() == ["reprojection"]
    e_t, e_r = errors(tp.T_camera_tag[0], geo.se3_from_rt(rot_deg(50, 10, 180), [0, 0, 1.0]))
    assert e_t < 1e-6 and e_r < 1e-4


def test_accepts_a_clean_square():
    tp = estimate_tag_poses(fake(SQUARE), K, [0.16], (640, 480))
    assert tp.accepted.tolist() == [True]
    # 80 px for 0.16 m at f = 615 px -> 1.23 m
    assert tp.T_camera_tag[0, 2, 3] == pytest.approx(0.16 * 615 / 80, rel=1e-3)
    cov = tp.covariance[0]
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_empty_detections():
    tp = estimate_tag_poses(TagDetections.empty(), K, np.zeros(0), (640, 480))
    assert tp.T_camera_tag.shape == (0, 4, 4) and tp.accepted.shape == (0,)
