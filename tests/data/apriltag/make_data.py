"""Regenerates tests/data/apriltag (run from the repository root): views + expected.json."""

import json

import cv2
import numpy as np
from dran_edge.perception.render import Lighting, TagRenderer

from dran_edge import geometry as geo

K = np.array([[615.0, 0, 319.5], [0, 615.0, 239.5], [0, 0, 1]])
r = TagRenderer()
rng = np.random.default_rng(2026)


def pose(yaw, pitch, roll, t):
    R = (
        geo.so3_exp(np.array([0, np.deg2rad(yaw), 0]))
        @ geo.so3_exp(np.array([np.deg2rad(pitch), 0, 0]))
        @ geo.so3_exp(np.array([0, 0, np.deg2rad(roll)]))
    )
    return geo.se3_from_rt(R, np.array(t, float))


scenes = {
    "two_tags_clean": dict(
        poses=[pose(0, 0, 180, [-0.25, 0, 1.0]), pose(35, -10, 170, [0.3, 0.05, 1.6])],
        ids=[0, 5],
        sizes=[0.16, 0.16],
        kw=dict(),
    ),
    "three_tags_clutter": dict(
        poses=[
            pose(-30, 10, 190, [-0.4, -0.1, 1.4]),
            pose(10, 0, 180, [0.05, 0.1, 2.2]),
            pose(45, 5, 200, [0.45, -0.05, 1.2]),
        ],
        ids=[12, 13, 42],
        sizes=[0.16, 0.16, 0.16],
        kw=dict(clutter=True, noise_sigma=3.0, blur_sigma_px=0.6),
    ),
    "lighting_gradient": dict(
        poses=[pose(20, 20, 160, [0.0, 0.0, 0.9])],
        ids=[100],
        sizes=[0.16],
        kw=dict(
            lighting=Lighting(gain=0.7, offset=10, gradient=0.4, gradient_angle_rad=0.5),
            noise_sigma=2.0,
        ),
    ),
    "small_far_tag": dict(
        poses=[pose(5, 0, 180, [0.1, 0.0, 3.5])], ids=[586], sizes=[0.16], kw=dict(noise_sigma=2.0)
    ),
}
S = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], float)
meta = {
    "K": K.tolist(),
    "width": 640,
    "height": 480,
    "note": (
        "rendered by perception/render.py (synthetic, not photographs); corners in the "
        "detector's convention (pixel centres at +0.5)"
    ),
    "images": {},
}
for name, sc in scenes.items():
    col, dep = r.render(K, 640, 480, sc["poses"], sc["ids"], sc["sizes"], rng=rng, **sc["kw"])
    cv2.imwrite(
        f"tests/data/apriltag/{name}.png",
        cv2.cvtColor(col, cv2.COLOR_BGR2GRAY),
        [cv2.IMWRITE_PNG_COMPRESSION, 9],
    )
    tags = []
    for T, i, s in zip(sc["poses"], sc["ids"], sc["sizes"]):
        P = S * s / 2
        pc = P @ T[:3, :3].T + T[:3, 3]
        uv = pc @ K.T
        uv = uv[:, :2] / uv[:, 2:] + 0.5
        tags.append(
            {
                "tag_id": i,
                "size_m": s,
                "corners": np.round(uv, 4).tolist(),
                "T_camera_tag": np.round(T, 9).tolist(),
            }
        )
    meta["images"][f"{name}.png"] = tags
json.dump(meta, open("tests/data/apriltag/expected.json", "w"), indent=1)
