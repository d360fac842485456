"""Calibration files: the tag -> object map and per-robot cameras (docs/calibration.md).

Loading is strict: unknown keys, missing keys, wrong types, out-of-range values, non-unit
quaternions and duplicate tag ids are rejected with the file, line and key path.

    calib/tags.yaml            format: dran-edge-tags/1
    calib/cameras/<robot>.yaml format: dran-edge-camera/1
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import ConfigError

TAGS_FORMAT = "dran-edge-tags/1"
CAMERA_FORMAT = "dran-edge-camera/1"


# --------------------------------------------------------------------------- YAML with lines
class _Map(dict):
    """A mapping that remembers the line (1-based) of each key."""

    lines: dict
    line: int


def _load_yaml(path: Path) -> Any:
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def construct_mapping(loader, node, deep=False):
        out = _Map()
        out.lines = {}
        out.line = node.start_mark.line + 1
        for key_node, value_node in node.value:
            key = loader.construct_object(key_node, deep=True)
            if key in out:
                raise ConfigError(
                    f"duplicate key {key!r}", path=str(path), line=key_node.start_mark.line + 1
                )
            out[key] = loader.construct_object(value_node, deep=True)
            out.lines[key] = key_node.start_mark.line + 1
        return out

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, construct_mapping)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror}", path=str(path)) from exc
    try:
        return yaml.load(text, Loader=Loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise ConfigError(
            f"not valid YAML: {getattr(exc, 'problem', exc)}",
            path=str(path),
            line=mark.line + 1 if mark else None,
        ) from exc


class _Reader:
    """Typed access to a loaded mapping with errors that carry file, line and key path."""

    def __init__(self, path: Path, node: Any, where: str = "", line: int | None = None):
        self.path, self.where = path, where
        if not isinstance(node, dict):
            raise ConfigError(
                f"{where or 'top level'}: expected a mapping, got {type(node).__name__}",
                path=str(path),
                line=line,
            )
        self.node = node
        self.line = getattr(node, "line", line)

    def fail(self, key: str | None, msg: str) -> ConfigError:
        line = self.node.lines.get(key, self.line) if hasattr(self.node, "lines") else self.line
        name = f"{self.where}.{key}" if (self.where and key) else (key or self.where)
        return ConfigError(f"{name}: {msg}", path=str(self.path), line=line)

    def check_keys(self, required: set[str], optional: set[str] = frozenset()) -> None:
        unknown = set(self.node) - required - set(optional)
        if unknown:
            raise self.fail(
                sorted(map(str, unknown))[0],
                f"unknown key; expected one of {sorted(required | set(optional))}",
            )
        missing = required - set(self.node)
        if missing:
            raise self.fail(None, f"missing key(s) {sorted(missing)}")

    def number(self, key: str, lo: float = -np.inf, hi: float = np.inf, default=None) -> float:
        v = self.node.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise self.fail(key, f"expected a finite number, got {v!r}")
        if not lo <= v <= hi:
            raise self.fail(key, f"expected {lo} <= value <= {hi}, got {v!r}")
        return float(v)

    def integer(self, key: str, lo: int = 0, hi: int = 2**31 - 1) -> int:
        v = self.node.get(key)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(key, f"expected an integer, got {v!r}")
        if not lo <= v <= hi:
            raise self.fail(key, f"expected {lo} <= value <= {hi}, got {v!r}")
        return v

    def string(self, key: str, default=None) -> str:
        v = self.node.get(key, default)
        if not isinstance(v, str) or not v:
            raise self.fail(key, f"expected a non-empty string, got {v!r}")
        return v

    def vector(self, key: str, n: int) -> np.ndarray:
        v = self.node.get(key)
        if (
            not isinstance(v, list)
            or len(v) != n
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)
            or not np.all(np.isfinite(v))
        ):
            raise self.fail(key, f"expected a list of {n} finite numbers, got {v!r}")
        return np.asarray(v, dtype=np.float64)

    def child(self, key: str) -> _Reader:
        line = self.node.lines.get(key) if hasattr(self.node, "lines") else None
        return _Reader(
            self.path, self.node.get(key), f"{self.where}.{key}" if self.where else key, line
        )

    def pose(self, key: str) -> np.ndarray:
        """``{xyz: [x, y, z], quat_xyzw: [qx, qy, qz, qw]}`` -> 4x4 (quaternion must be unit)."""
        r = self.child(key)
        r.check_keys({"xyz", "quat_xyzw"})
        xyz, q = r.vector("xyz", 3), r.vector("quat_xyzw", 4)
        if abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise r.fail(
                "quat_xyzw", f"expected a unit quaternion, got norm {np.linalg.norm(q):.6f}"
            )
        return geo.se3_from_xyz_quat_xyzw(np.concatenate([xyz, q / np.linalg.norm(q)]))


# --------------------------------------------------------------------------- tags
@dataclass(frozen=True, eq=False)
class TagMap:
    """Which object each tag belongs to. Arrays are indexed by position ``k``; ``index`` maps
    ``tag_id -> k``. ``T_object_tag (k, 4, 4)``; ``size_m (k,)`` black-square edge in metres."""

    family: str
    tag_id: np.ndarray
    object_id: np.ndarray
    T_object_tag: np.ndarray
    size_m: np.ndarray
    object_names: dict

    def __post_init__(self) -> None:
        object.__setattr__(self, "_index", {int(t): k for k, t in enumerate(self.tag_id)})
        # precomputed for the per-frame path: T_tag_object and Adj(T_object_tag)
        object.__setattr__(self, "T_tag_object", geo.se3_inverse(self.T_object_tag))
        object.__setattr__(self, "adjoint_object_tag", geo.se3_adjoint(self.T_object_tag))
        half = (
            self.size_m[:, None, None]
            / 2
            * np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]])[None]
        )  # detector corner order
        object.__setattr__(
            self,
            "corners_object",
            np.einsum("kij,knj->kni", self.T_object_tag[:, :3, :2], half)
            + self.T_object_tag[:, None, :3, 3],
        )

    @property
    def index(self) -> dict:
        return dict(self._index)

    def lookup(self, tag_ids: np.ndarray) -> np.ndarray:
        """Positions ``(n,)`` of the given tag ids in this map, -1 for unknown tags."""
        get = self._index.get
        return np.fromiter((get(int(t), -1) for t in tag_ids), np.int64, len(tag_ids))


def load_tag_map(path: str | Path) -> TagMap:
    """Load ``tags.yaml`` (docs/calibration.md)."""
    path = Path(path)
    top = _Reader(path, _load_yaml(path))
    top.check_keys({"format", "family", "objects"})
    if top.node["format"] != TAGS_FORMAT:
        raise top.fail("format", f"expected {TAGS_FORMAT!r}, got {top.node['format']!r}")
    family = top.string("family")
    objects = top.node["objects"]
    if not isinstance(objects, list) or not objects:
        raise top.fail("objects", "expected a non-empty list of objects")
    tag_ids, object_ids, poses, sizes, names = [], [], [], [], {}
    seen: dict[int, str] = {}
    for i, obj_node in enumerate(objects):
        obj = _Reader(path, obj_node, f"objects[{i}]", top.node.lines.get("objects"))
        obj.check_keys({"id", "tags"}, {"name"})
        oid = obj.integer("id")
        if oid in names:
            raise obj.fail("id", f"object id {oid} appears twice")
        names[oid] = obj.string("name") if "name" in obj.node else f"object{oid}"
        tags = obj.node["tags"]
        if not isinstance(tags, list) or not tags:
            raise obj.fail("tags", "expected a non-empty list of tags")
        for j, tag_node in enumerate(tags):
            tag = _Reader(path, tag_node, f"{obj.where}.tags[{j}]", obj.node.lines.get("tags"))
            tag.check_keys({"tag_id", "size_m", "T_object_tag"})
            tid = tag.integer("tag_id", 0, 586 if family == "tag36h11" else 2**31 - 1)
            if tid in seen:
                raise tag.fail("tag_id", f"tag {tid} already used by {seen[tid]}")
            seen[tid] = f"objects[{i}]"
            tag_ids.append(tid)
            object_ids.append(oid)
            sizes.append(tag.number("size_m", 0.005, 2.0))
            poses.append(tag.pose("T_object_tag"))
    return TagMap(
        family,
        np.asarray(tag_ids, np.int64),
        np.asarray(object_ids, np.int64),
        np.stack(poses),
        np.asarray(sizes),
        names,
    )


# --------------------------------------------------------------------------- cameras
@dataclass(frozen=True, eq=False)
class CameraCalib:
    """One robot's colour camera: pinhole intrinsics and the camera's pose in the body frame."""

    robot: str
    width: int
    height: int
    K: np.ndarray
    """3x3 intrinsics, OpenCV convention (pixel centres at integer coordinates)."""
    distortion: np.ndarray
    """OpenCV plumb-bob [k1, k2, p1, p2, k3] (zeros for the D435i colour stream)."""
    T_body_camera: np.ndarray
    """Colour optical frame (x right, y down, z forward) in the body (VIO IMU) frame."""
    depth_unit_m: float = 0.001
    """Metres per depth count of the aligned depth image."""


def load_camera(path: str | Path) -> CameraCalib:
    """Load ``cameras/<robot>.yaml`` (docs/calibration.md)."""
    path = Path(path)
    top = _Reader(path, _load_yaml(path))
    top.check_keys(
        {"format", "robot", "width", "height", "intrinsics", "T_body_camera"},
        {"distortion", "depth_unit_m", "model"},
    )
    if top.node["format"] != CAMERA_FORMAT:
        raise top.fail("format", f"expected {CAMERA_FORMAT!r}, got {top.node['format']!r}")
    width, height = top.integer("width", 16, 10000), top.integer("height", 16, 10000)
    intr = top.child("intrinsics")
    intr.check_keys({"fx", "fy", "cx", "cy"})
    fx, fy = intr.number("fx", 1.0, 1e5), intr.number("fy", 1.0, 1e5)
    cx, cy = intr.number("cx", 0.0, width), intr.number("cy", 0.0, height)
    dist = top.vector("distortion", 5) if "distortion" in top.node else np.zeros(5)
    if "model" in top.node:
        top.string("model")
    return CameraCalib(
        robot=top.string("robot"),
        width=width,
        height=height,
        K=np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
        distortion=dist,
        T_body_camera=top.pose("T_body_camera"),
        depth_unit_m=top.number("depth_unit_m", 1e-6, 1.0) if "depth_unit_m" in top.node else 0.001,
    )


@dataclass(frozen=True, eq=False)
class Calibration:
    """What the pipeline needs: one camera and the fleet's tag map."""

    camera: CameraCalib
    tags: TagMap


def load_calibration(calib_dir: str | Path, robot: str) -> Calibration:
    """``<calib_dir>/tags.yaml`` and ``<calib_dir>/cameras/<robot>.yaml``."""
    calib_dir = Path(calib_dir)
    camera_path = calib_dir / "cameras" / f"{robot}.yaml"
    if not camera_path.exists():
        known = sorted(p.stem for p in (calib_dir / "cameras").glob("*.yaml"))
        raise ConfigError(
            f"no camera file for robot {robot!r}; found {known}", path=str(camera_path)
        )
    camera = load_camera(camera_path)
    if camera.robot != robot:
        raise ConfigError(
            f"robot: expected {robot!r} (the file name), got {camera.robot!r}",
            path=str(camera_path),
        )
    return Calibration(camera=camera, tags=load_tag_map(calib_dir / "tags.yaml"))
