"""Synthetic camera views of AprilTags with known poses (tests, benchmarks, simulated missions).

Conventions (docs/perception.md, "Renderer"):

- Camera: OpenCV pinhole, x right, y down, z forward; ``K`` maps camera points to pixels whose
  centres are at integer coordinates (OpenCV). No distortion (D435i colour has none).
- Tag frame: pupil-apriltags' own (centre of the tag, x right, y down, z into the tag as seen by
  the viewer when ``R_camera_tag = I``); ``tag_size_m`` is the edge of the black square.
- Texture: OpenCV's ``DICT_APRILTAG_36h11`` markers decode to the same ids in pupil-apriltags.
  An OpenCV marker drawn upright in the image has ``R_camera_tag = Rz(180 deg)`` in that frame
  (docs/perception.md), so the texture's +u axis is the tag's -x and +v is -y. The renderer
  applies this so that ``T_camera_tag`` given here is exactly what the detector should recover.
- Each tag is pasted with a white quiet zone of ``quiet_zone_modules`` modules around the black
  square, drawn back to front. Depth (uint16 mm) is the exact plane depth of that face;
  elsewhere ``background_depth_mm`` (0 = no data, like a RealSense hole).

Speed: each tag is one ``warpPerspective`` into its bounding box, from a binary texture whose
module size is the smallest level >= the projected module size (a mip level, so edges are
neither aliased nor over-blurred); noise comes from a pre-drawn pool at a random offset.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dran_edge.errors import InputError

_LEVELS_PX = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)
_NEAR_M = 0.05


@dataclass(frozen=True)
class Lighting:
    """Illumination: ``out = gain * (1 + gradient * ramp) * img + offset`` (grey levels 0..255).

    ``ramp`` runs linearly from -1 to +1 along ``gradient_angle_rad`` (image axes) across the frame.
    """

    gain: float = 1.0
    """Multiplicative gain (contrast)."""
    offset: float = 0.0
    """Additive offset in grey levels."""
    gradient: float = 0.0
    """Relative gain change across the image (0.3 = +-30 %)."""
    gradient_angle_rad: float = 0.0
    """Direction of the gradient in the image plane (0 = left to right)."""


@dataclass(frozen=True)
class DepthModel:
    """Synthetic depth noise like a stereo camera: sigma_z = ``coeff_per_m`` * z^2, in metres."""

    coeff_per_m: float = 0.002
    """sigma of depth at 1 m in metres (D435i at 640x480 is roughly 1-2 mm/m^2 at short range)."""
    background_depth_mm: int = 0
    """Depth written where no tag face is drawn (0 = no data)."""


class TagRenderer:
    """Caches textures, background and a noise pool; ``render`` draws one view.

    One renderer per thread. ``family`` must be tag36h11 (the dictionary OpenCV provides that
    matches the detector's default).
    """

    def __init__(
        self,
        family: str = "tag36h11",
        quiet_zone_modules: int = 2,
        background_seed: int = 7,
        noise_pool_size: int = 1 << 21,
    ) -> None:
        import cv2

        if family != "tag36h11":
            raise InputError(f"renderer family: expected 'tag36h11', got {family!r}")
        self._cv2 = cv2
        self._dict = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
        self.quiet_zone_modules = int(quiet_zone_modules)
        self._bits: dict[int, np.ndarray] = {}
        self._tex: dict[tuple[int, int], np.ndarray] = {}
        self._backgrounds: dict[tuple[int, int], np.ndarray] = {}
        self._background_seed = background_seed
        pool_rng = np.random.default_rng(background_seed + 1)
        self._noise_pool = pool_rng.standard_normal(noise_pool_size, dtype=np.float32)

    # ------------------------------------------------------------------ textures
    def _tag_bits(self, tag_id: int) -> np.ndarray:
        bits = self._bits.get(tag_id)
        if bits is None:
            n_codes = self._dict.bytesList.shape[0]
            if not (0 <= tag_id < n_codes):
                raise InputError(f"tag id: expected 0..{n_codes - 1} for tag36h11, got {tag_id}")
            marker = self._cv2.aruco.generateImageMarker(self._dict, int(tag_id), 8, borderBits=1)
            q = self.quiet_zone_modules
            bits = np.pad(marker, q, constant_values=255)
            self._bits[tag_id] = bits
        return bits

    def texture(self, tag_id: int, module_px: int) -> np.ndarray:
        """The tag with its quiet zone, ``module_px`` px per module, upright as OpenCV draws it."""
        key = (tag_id, module_px)
        tex = self._tex.get(key)
        if tex is None:
            tex = np.repeat(np.repeat(self._tag_bits(tag_id), module_px, 0), module_px, 1)
            self._tex[key] = tex
        return tex

    def background(self, width: int, height: int, clutter: bool = False) -> np.ndarray:
        """A fixed textured grey background: smooth blobs plus a few edges, or with
        ``clutter=True`` an indoor-like scene (many overlapping rectangles such as shelves,
        boxes and posters, thin edges, fine texture) that gives the quad detector the kind of
        edge content real frames have."""
        key = (width, height, clutter)
        bg = self._backgrounds.get(key)
        if bg is None:
            cv2 = self._cv2
            rng = np.random.default_rng(self._background_seed)
            coarse = rng.uniform(70, 190, size=(height // 32 + 2, width // 32 + 2))
            bg = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
            if clutter:
                for _ in range(60):
                    x, y = rng.integers(0, [width, height])
                    dx, dy = rng.integers(8, [160, 120])
                    cv2.rectangle(
                        bg,
                        (int(x), int(y)),
                        (int(x + dx), int(y + dy)),
                        float(rng.uniform(30, 230)),
                        -1 if rng.random() < 0.7 else 2,
                    )
                fine = rng.normal(0, 12, size=(height // 4 + 1, width // 4 + 1))
                bg += cv2.resize(fine, (width, height), interpolation=cv2.INTER_LINEAR)
            for _ in range(30 if clutter else 12):
                p0 = rng.integers(0, [width, height])
                p1 = p0 + rng.integers(-200, 200, size=2)
                level = float(rng.uniform(60, 200))
                cv2.line(
                    bg,
                    tuple(int(v) for v in p0),
                    tuple(int(v) for v in p1),
                    level,
                    int(rng.integers(1, 4)) if clutter else 3,
                )
            bg = np.clip(bg, 0, 255).astype(np.uint8)
            self._backgrounds[key] = bg
        return bg

    # ------------------------------------------------------------------ render
    def render(
        self,
        K: np.ndarray,
        width: int,
        height: int,
        T_camera_tag: Sequence[np.ndarray] | np.ndarray,
        tag_ids: Sequence[int],
        tag_sizes_m: Sequence[float] | float,
        blur_sigma_px: float = 0.0,
        noise_sigma: float = 0.0,
        lighting: Lighting | None = None,
        occlusion: Sequence[float] | float = 0.0,
        rng: np.random.Generator | None = None,
        depth: DepthModel | None = None,
        background: np.ndarray | None = None,
        clutter: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Draw the tags; returns ``(colour BGR uint8 (H, W, 3), depth uint16 mm (H, W))``.

        ``occlusion`` (per tag or one value) is the fraction in [0, 1) of the tag's face covered
        by a flat grey band entering from a random side. ``noise_sigma`` is grey-level noise,
        ``blur_sigma_px`` a Gaussian blur of the whole image. ``depth=None`` uses ``DepthModel()``;
        pass ``DepthModel(coeff_per_m=0)`` for exact depth. ``rng`` drives noise and occlusion.
        """
        cv2 = self._cv2
        rng = rng if rng is not None else np.random.default_rng(0)
        depth = depth if depth is not None else DepthModel()
        K = np.asarray(K, dtype=np.float64)
        poses = np.asarray(T_camera_tag, dtype=np.float64).reshape(-1, 4, 4)
        n = poses.shape[0]
        ids = [int(i) for i in tag_ids]
        sizes = np.broadcast_to(np.asarray(tag_sizes_m, dtype=np.float64), (n,))
        occ = np.broadcast_to(np.asarray(occlusion, dtype=np.float64), (n,))
        if len(ids) != n:
            raise InputError(f"render: {n} poses but {len(ids)} tag ids")
        if background is None:
            gray = self.background(width, height, clutter).copy()
        else:
            gray = np.ascontiguousarray(background, dtype=np.uint8).copy()
        depth_mm = np.full((height, width), depth.background_depth_mm, np.uint16)
        order = np.argsort(-poses[:, 2, 3])  # far to near
        for k in order:
            self._draw_tag(
                gray, depth_mm, K, poses[k], ids[k], float(sizes[k]), float(occ[k]), rng, depth
            )
        img = gray.astype(np.float32) if (lighting or noise_sigma > 0) else gray
        if lighting is not None:
            img = self._apply_lighting(img, lighting)
        if noise_sigma > 0:
            img = img + noise_sigma * self._noise(img.shape, rng)
        if img.dtype != np.uint8:
            img = np.clip(img + 0.5, 0, 255).astype(np.uint8)
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), depth_mm

    def _noise(self, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        count = int(np.prod(shape))
        pool = self._noise_pool
        if count > pool.size:
            return rng.standard_normal(shape, dtype=np.float32)
        start = int(rng.integers(0, pool.size - count + 1))
        return pool[start : start + count].reshape(shape)

    def _apply_lighting(self, img: np.ndarray, lighting: Lighting) -> np.ndarray:
        h, w = img.shape
        gain = np.float32(lighting.gain)
        if lighting.gradient != 0.0:
            c, s = np.cos(lighting.gradient_angle_rad), np.sin(lighting.gradient_angle_rad)
            x = np.linspace(-1, 1, w, dtype=np.float32)[None, :]
            y = np.linspace(-1, 1, h, dtype=np.float32)[:, None]
            ramp = (c * x + s * y) / max(abs(c) + abs(s), 1e-9)
            gain = gain * (1 + np.float32(lighting.gradient) * ramp)
        return img * gain + np.float32(lighting.offset)

    def _draw_tag(self, gray, depth_mm, K, T, tag_id, size_m, occlusion, rng, depth) -> None:
        cv2 = self._cv2
        height, width = gray.shape
        q = self.quiet_zone_modules
        half_face = size_m / 2 * (8 + 2 * q) / 8
        face_tag = np.array(
            [
                [-half_face, -half_face],
                [half_face, -half_face],
                [half_face, half_face],
                [-half_face, half_face],
            ]
        )
        R, t = T[:3, :3], T[:3, 3]
        face_cam = face_tag @ R[:, :2].T + t
        if np.any(face_cam[:, 2] < _NEAR_M):
            return
        uv = face_cam @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        x0 = int(max(np.floor(uv[:, 0].min()) - 1, 0))
        y0 = int(max(np.floor(uv[:, 1].min()) - 1, 0))
        x1 = int(min(np.ceil(uv[:, 0].max()) + 2, width))
        y1 = int(min(np.ceil(uv[:, 1].max()) + 2, height))
        if x1 <= x0 or y1 <= y0:
            return
        edge_px = np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1).max()
        module_img_px = edge_px / (8 + 2 * q)
        module_px = next((m for m in _LEVELS_PX if m >= module_img_px), _LEVELS_PX[-1])
        tex = self.texture(tag_id, module_px)
        n_tex = tex.shape[0]
        # texture (u, v) with pixel centres at integers -> tag (x, y): u grows along -x, v along -y
        scale = 2 * half_face / n_tex
        A_tag_tex = np.array(
            [
                [-scale, 0.0, half_face - 0.5 * scale],
                [0.0, -scale, half_face - 0.5 * scale],
                [0.0, 0.0, 1.0],
            ]
        )
        H_img_tag = K @ np.column_stack([R[:, 0], R[:, 1], t])
        shift = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]])
        H = shift @ H_img_tag @ A_tag_tex
        roi = gray[y0:y1, x0:x1]
        cv2.warpPerspective(
            tex,
            H,
            (x1 - x0, y1 - y0),
            dst=roi,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_TRANSPARENT,
        )
        if occlusion > 0:
            self._occlude(gray, K, R, t, half_face, size_m, occlusion, rng)
        # plane depth over the face: n . X = d in camera coordinates, X = z * K^-1 [u, v, 1]
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(
            mask, np.round((uv - [x0, y0]) * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4
        )
        vv, uu = np.nonzero(mask)
        if vv.size == 0:
            return
        normal = R[:, 2]
        Kinv = np.linalg.inv(K)
        rays = Kinv[:, 0:1] * (uu + x0) + Kinv[:, 1:2] * (vv + y0) + Kinv[:, 2:3]
        denom = normal @ rays
        z = np.where(np.abs(denom) > 1e-9, (normal @ t) / np.where(denom == 0, 1, denom), 0.0)
        if depth.coeff_per_m > 0:
            z = z + depth.coeff_per_m * z * z * rng.standard_normal(z.shape)
        depth_mm[vv + y0, uu + x0] = np.clip(np.round(z * 1000.0), 0, 65535).astype(np.uint16)

    def _occlude(self, gray, K, R, t, half_face, size_m, fraction, rng) -> None:
        """A grey band over ``fraction`` of the black square, entering from a random side."""
        cv2 = self._cv2
        s = size_m / 2
        depth_into = 2 * s * min(max(fraction, 0.0), 0.99)
        side = int(rng.integers(4))
        lo = -half_face
        band = {
            0: [[lo, lo], [half_face, lo], [half_face, -s + depth_into], [lo, -s + depth_into]],
            1: [
                [s - depth_into, lo],
                [half_face, lo],
                [half_face, half_face],
                [s - depth_into, half_face],
            ],
            2: [
                [lo, s - depth_into],
                [half_face, s - depth_into],
                [half_face, half_face],
                [lo, half_face],
            ],
            3: [[lo, lo], [-s + depth_into, lo], [-s + depth_into, half_face], [lo, half_face]],
        }[side]
        cam = np.asarray(band) @ R[:, :2].T + t
        uv = cam @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        level = int(rng.integers(90, 170))
        cv2.fillConvexPoly(gray, np.round(uv * 16).astype(np.int32), level, cv2.LINE_AA, 4)


def write_realsense_recording(
    path, frames, K: np.ndarray, fps: int = 30, depth_unit_m: float = 0.001
) -> int:
    """Write frames (``frame.Frame``) as a RealSense recording through pyrealsense2 itself.

    A ``software_device`` with a colour sensor (bgr8) and a depth sensor (z16, already aligned:
    same intrinsics, identity extrinsics) is recorded by ``rs.recorder``; stamps go in as
    global-time milliseconds. librealsense 2.56+ writes only ``.db3`` (rosbag2/SQLite) files
    ("Output file must have .db3 extension"). Returns the number of frames written.
    """
    import pyrealsense2 as rs

    frames = list(frames)
    if not frames:
        raise InputError("write_realsense_recording: no frames")
    h, w = frames[0].colour.shape[:2]
    K = np.asarray(K, dtype=np.float64)
    intr = rs.intrinsics()
    intr.width, intr.height = w, h
    intr.fx, intr.fy, intr.ppx, intr.ppy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    intr.model = rs.distortion.none
    intr.coeffs = [0.0] * 5
    device = rs.software_device()
    colour_sensor = device.add_sensor("RGB Camera")
    depth_sensor = device.add_sensor("Stereo Module")

    def stream(kind, uid, bpp, fmt):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = w, h, fps, bpp, fmt
        vs.intrinsics = intr
        return vs

    colour_profile = colour_sensor.add_video_stream(stream(rs.stream.color, 0, 3, rs.format.bgr8))
    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, 1, 2, rs.format.z16))
    depth_sensor.add_read_only_option(rs.option.depth_units, float(depth_unit_m))
    identity = rs.extrinsics()
    identity.rotation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    identity.translation = [0.0, 0.0, 0.0]
    depth_profile.register_extrinsics_to(colour_profile, identity)
    recorder = rs.recorder(str(path), device)
    queue = rs.frame_queue(64)
    colour_sensor.open(colour_profile)
    depth_sensor.open(depth_profile)
    colour_sensor.start(queue)
    depth_sensor.start(queue)
    try:
        for number, fr in enumerate(frames):
            pairs = [(colour_sensor, colour_profile, np.ascontiguousarray(fr.colour), 3)]
            if fr.depth is not None:
                pairs.append((depth_sensor, depth_profile, np.ascontiguousarray(fr.depth), 2))
            for sensor, profile, pixels, bpp in pairs:
                f = rs.software_video_frame()
                f.pixels, f.stride, f.bpp = pixels, w * bpp, bpp
                f.timestamp = fr.stamp_ns / 1e6
                f.domain = rs.timestamp_domain.global_time
                f.frame_number = number
                f.profile = profile.as_video_stream_profile()
                sensor.on_video_frame(f)
            while queue.poll_for_frame():
                pass
    finally:
        for s in (colour_sensor, depth_sensor):
            s.stop()
            s.close()
        del recorder
    return len(frames)
