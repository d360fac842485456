"""Detector wrapper, renderer conventions and the committed test images."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pupil_apriltags")
cv2 = pytest.importorskip("cv2")

from dran_edge.perception.detector import DetectorParams, TagDetector, to_gray  # noqa: E402
from dran_edge.perception.render import DepthModel, TagRenderer  # noqa: E402
from dran_edge.perception.tagpose import UNIT_CORNERS  # noqa: E402

from dran_edge import geometry as geo  # noqa: E402
from dran_edge.errors import ConfigError, InputError  # noqa: E402

DATA = Path(__file__).parent / "data" / "apriltag"
K = np.array([[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]])


def project_corners(T: np.ndarray, size_m: float) -> np.ndarray:
    """Exact tag corners in OpenCV pixel convention (centres at integers)."""
    p = UNIT_CORNERS * size_m / 2 @ T[:3, :3].T + T[:3, 3]
    uv = p @ K.T
    return uv[:, :2] / uv[:, 2:]


def test_one_family_only():
    with pytest.raises(ConfigError, match="exactly one"):
        DetectorParams(family="tag36h11 tag25h9")
    with pytest.raises(ConfigError):
        DetectorParams(quad_decimate=0.5)


def test_decode_sharpening_not_truncated_and_logged(caplog):
    with caplog.at_level(logging.INFO, logger="dran_edge.perception.detector"):
        det = TagDetector(DetectorParams(decode_sharpening=0.25, quad_decimate=1.5, nthreads=2))
    assert det.in_force["decode_sharpening"] == pytest.approx(0.25)  # the binding alone gives 0
    assert det.in_force["quad_decimate"] == pytest.approx(1.5)
    assert det.in_force["nthreads"] == 2
    assert det.in_force["family"] == "tag36h11"
    assert "decode_sharpening" in caplog.text and "0.25" in caplog.text


def test_rejects_colour_input():
    with pytest.raises(InputError, match="2-D uint8"):
        TagDetector().detect(np.zeros((4, 4, 3), np.uint8))


def test_close_is_idempotent_and_detect_after_close_fails():
    det = TagDetector()
    det.close()
    det.close()
    with pytest.raises(Exception, match="after close"):
        det.detect(np.zeros((8, 8), np.uint8))


def test_detect_prints_nothing(capfd):
    colour, _ = TagRenderer().render(
        K, 640, 480, [geo.se3_from_rt(np.eye(3), [0, 0, 1.0])], [3], 0.16
    )
    TagDetector().detect(to_gray(colour))
    out, _ = capfd.readouterr()
    assert out == ""


def test_renderer_corner_convention_and_ids():
    """Detected corners = exact projection + 0.5 px (AprilTag pixel centres at half-integers),
    same ids as OpenCV's dictionary, pupil-apriltags' corner order."""
    rng = np.random.default_rng(3)
    renderer, det = TagRenderer(), TagDetector(DetectorParams(quad_decimate=1.0))
    offsets = []
    for tag_id in (0, 1, 42, 100, 586):
        R = geo.so3_exp(rng.uniform(-0.5, 0.5, 3))
        T = geo.se3_from_rt(R, [rng.uniform(-0.2, 0.2), rng.uniform(-0.1, 0.1), 1.2])
        colour, _ = renderer.render(K, 640, 480, [T], [tag_id], 0.16)
        d = det.detect(to_gray(colour))
        assert d.tag_id.tolist() == [tag_id]
        assert d.hamming[0] == 0
        offsets.append(d.corners[0] - project_corners(T, 0.16))
    offsets = np.array(offsets).reshape(-1, 2)
    assert np.allclose(offsets.mean(0), 0.5, atol=0.05)
    assert np.abs(offsets - 0.5).max() < 0.3


def test_upright_opencv_marker_is_rz180():
    """docs/perception.md: an OpenCV marker drawn upright has R_camera_tag = Rz(180)."""
    renderer = TagRenderer()
    Rz180 = np.diag([-1.0, -1.0, 1.0])
    colour, _ = renderer.render(K, 640, 480, [geo.se3_from_rt(Rz180, [0, 0, 1.0])], [7], 0.16)
    marker = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), 7, 8, borderBits=1
    )
    # sample the module centres of the rendered black square (8 modules, ~12.3 px each)
    corners = project_corners(geo.se3_from_rt(Rz180, [0, 0, 1.0]), 0.16)
    x0, y0 = corners.min(0)
    x1, y1 = corners.max(0)
    xs = x0 + (np.arange(8) + 0.5) * (x1 - x0) / 8
    ys = y0 + (np.arange(8) + 0.5) * (y1 - y0) / 8
    grey = to_gray(colour)
    sampled = grey[np.round(ys).astype(int)[:, None], np.round(xs).astype(int)[None, :]]
    assert np.array_equal(sampled > 127, marker > 127)


def test_rendered_depth_is_plane_depth():
    T = geo.se3_from_rt(geo.so3_exp(np.array([0.0, 0.5, 0.0])), [0.1, 0.0, 1.5])
    _, depth = TagRenderer().render(
        K, 640, 480, [T], [1], 0.16, depth=DepthModel(coeff_per_m=0.0, background_depth_mm=0)
    )
    u, v = np.rint(project_corners(T, 0.0)[0]).astype(int)  # the tag centre
    assert depth[v, u] == pytest.approx(1500, abs=2)
    assert depth[0, 0] == 0
    assert np.count_nonzero(depth) > 1000


def test_committed_images_within_half_pixel():
    meta = json.loads((DATA / "expected.json").read_text())
    det = TagDetector(DetectorParams(quad_decimate=2.0))
    seen = 0
    for name, tags in meta["images"].items():
        grey = cv2.imread(str(DATA / name), cv2.IMREAD_GRAYSCALE)
        d = det.detect(grey)
        assert sorted(d.tag_id.tolist()) == sorted(t["tag_id"] for t in tags), name
        for t in tags:
            k = d.tag_id.tolist().index(t["tag_id"])
            err = np.abs(d.corners[k] - np.asarray(t["corners"])).max()
            assert err < 0.5, (name, t["tag_id"], err)
            seen += 1
    assert seen == 7
