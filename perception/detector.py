"""AprilTag detection with pupil-apriltags: one pinned family, explicit parameters.

The binding (pupil-apriltags 1.0.4.x, docs/perception.md) has three traps this wrapper closes:

- it adds only ONE family (an ``if/elif`` chain over the space-separated string), silently
  dropping the rest: we accept exactly one known family name and refuse anything else;
- it assigns ``int(decode_sharpening)`` into the C ``double`` field, so the documented default
  0.25 becomes 0.0: after construction we write the float into the C struct directly and read it
  back, and log the value actually in force;
- its pose estimator (``estimate_tag_pose=True``) can print to stdout from C: we never call it.
  Pose comes from the corners (``tagpose.py``);
- its ``__del__`` destroys the tag family before the detector, and
  ``apriltag_detector_destroy`` then clears the family's quick-decode table through the freed
  family (use after free: the rare "corrupted size vs. prev_size" / segfault at interpreter
  exit). ``TagDetector.close()`` (also run by ``__del__``) destroys them in the right order and
  disarms the binding's destructor.

Corner convention (the library's, kept in our output): ``corners[i]`` for i = 0..3 are the
image points of the tag-frame points (-s, +s), (+s, +s), (+s, -s), (-s, -s) with s = size/2
(counter-clockwise on screen). AprilTag 3 places pixel centres at half-integers: the top-left
pixel covers [0, 1) x [0, 1). OpenCV puts pixel centres at integers; ``tagpose.py`` converts
(``CORNER_TO_OPENCV_PX``), measured in tests/test_perception_detector.py.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np

from dran_edge.errors import ConfigError, DependencyError, InputError

log = logging.getLogger(__name__)

FAMILIES = (
    "tag16h5",
    "tag25h9",
    "tag36h11",
    "tagCircle21h7",
    "tagCircle49h12",
    "tagCustom48h12",
    "tagStandard41h12",
    "tagStandard52h13",
)


@dataclass(frozen=True)
class DetectorParams:
    """Parameters of the AprilTag detector (all passed explicitly to the C library)."""

    family: str = "tag36h11"
    """The one tag family searched for (one of ``FAMILIES``)."""
    nthreads: int = 1
    """Worker threads inside the C detector."""
    quad_decimate: float = 2.0
    """Quad detection runs on an image decimated by this factor (decoding is at full size)."""
    quad_sigma: float = 0.0
    """Gaussian blur sigma in pixels applied before quad segmentation (0 = none)."""
    refine_edges: bool = True
    """Snap quad edges to strong gradients (recommended with decimation)."""
    decode_sharpening: float = 0.25
    """Sharpening of the decoded samples (upstream default 0.25; set in C unrounded)."""

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ConfigError(
                f"detector family: expected exactly one of {', '.join(FAMILIES)}, "
                f"got {self.family!r} (the binding silently keeps only one family)"
            )
        if int(self.nthreads) != self.nthreads or self.nthreads < 1:
            raise ConfigError(f"detector nthreads: expected an integer >= 1, got {self.nthreads!r}")
        if not (1.0 <= float(self.quad_decimate) <= 8.0):
            raise ConfigError(
                f"detector quad_decimate: expected 1.0 <= value <= 8.0, got {self.quad_decimate!r}"
            )
        if not (0.0 <= float(self.quad_sigma) <= 5.0):
            raise ConfigError(
                f"detector quad_sigma: expected 0 <= value <= 5 px, got {self.quad_sigma!r}"
            )
        if not (0.0 <= float(self.decode_sharpening) <= 10.0):
            raise ConfigError(
                "detector decode_sharpening: expected 0 <= value <= 10, "
                f"got {self.decode_sharpening!r}"
            )


@dataclass(frozen=True, eq=False)
class TagDetections:
    """The detections of one image, as arrays (n = number of tags).

    ``corners`` is ``(n, 4, 2)`` float64 in the library's order and pixel convention (see the
    module docstring); ``tag_id``, ``hamming`` int arrays; ``decision_margin`` float array.
    """

    tag_id: np.ndarray
    hamming: np.ndarray
    decision_margin: np.ndarray
    corners: np.ndarray

    def __len__(self) -> int:
        return int(self.tag_id.shape[0])

    @staticmethod
    def empty() -> TagDetections:
        return TagDetections(
            np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 4, 2))
        )


class TagDetector:
    """A pupil-apriltags detector pinned to one family.

    ``detect(gray)`` takes a 2-D uint8 image and returns ``TagDetections``. The detector holds C
    state and is not thread-safe: use one per thread.
    """

    def __init__(self, params: DetectorParams | None = None) -> None:
        self.params = params or DetectorParams()
        try:
            import pupil_apriltags
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise DependencyError(
                "pupil-apriltags is needed for tag detection: pip install 'dran-edge[perception]'"
            ) from exc
        p = self.params
        self._detector = pupil_apriltags.Detector(
            families=p.family,
            nthreads=int(p.nthreads),
            quad_decimate=float(p.quad_decimate),
            quad_sigma=float(p.quad_sigma),
            refine_edges=int(bool(p.refine_edges)),
            decode_sharpening=float(p.decode_sharpening),
            debug=0,
        )
        c = self._detector.tag_detector_ptr.contents
        # The binding stores int(decode_sharpening) (0.25 -> 0.0); write the float ourselves.
        c.decode_sharpening = float(p.decode_sharpening)
        self.in_force = {
            "family": ",".join(self._detector.tag_families.keys()),
            "nthreads": int(c.nthreads),
            "quad_decimate": float(c.quad_decimate),
            "quad_sigma": float(c.quad_sigma),
            "refine_edges": int(c.refine_edges),
            "decode_sharpening": float(c.decode_sharpening),
            "binding_version": getattr(pupil_apriltags, "__version__", "unknown"),
        }
        if self.in_force["family"] != p.family:
            raise DependencyError(
                f"pupil-apriltags added family {self.in_force['family']!r}, expected {p.family!r}"
            )
        if abs(self.in_force["decode_sharpening"] - float(p.decode_sharpening)) > 1e-12:
            raise DependencyError(
                "pupil-apriltags decode_sharpening: wrote "
                f"{p.decode_sharpening}, C struct holds {self.in_force['decode_sharpening']}"
            )
        log.info("AprilTag detector parameters in force: %s (asked: %s)", self.in_force, asdict(p))

    def close(self) -> None:
        """Free the C detector, then its family (the reverse of the binding's order)."""
        d = getattr(self, "_detector", None)
        if d is None or d.tag_detector_ptr is None:
            return
        libc = d.libc
        libc.apriltag_detector_destroy.restype = None
        libc.apriltag_detector_destroy(d.tag_detector_ptr)  # uses the families: before them
        for name, family in d.tag_families.items():
            destroy = getattr(libc, f"{name}_destroy")
            destroy.restype = None
            destroy(family)
        d.tag_families = {}
        d.tag_detector_ptr = None  # the binding's __del__ now does nothing
        self._detector = None

    def __del__(self) -> None:
        self.close()

    def detect(self, gray: np.ndarray) -> TagDetections:
        """Detect tags in a 2-D uint8 image (C-contiguous or not)."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise InputError(
                f"detector input: expected a 2-D uint8 grey image, got shape {gray.shape} "
                f"dtype {gray.dtype}"
            )
        if self._detector is None:
            raise DependencyError("TagDetector.detect after close()")
        dets = self._detector.detect(gray, estimate_tag_pose=False)
        n = len(dets)
        if n == 0:
            return TagDetections.empty()
        return TagDetections(
            tag_id=np.fromiter((d.tag_id for d in dets), np.int64, n),
            hamming=np.fromiter((d.hamming for d in dets), np.int64, n),
            decision_margin=np.fromiter((d.decision_margin for d in dets), np.float64, n),
            corners=np.stack([d.corners for d in dets]).astype(np.float64, copy=False),
        )


def to_gray(colour_bgr: np.ndarray) -> np.ndarray:
    """BGR uint8 (H, W, 3) -> grey (H, W) uint8 (OpenCV BT.601 weights); grey passes through."""
    import cv2

    if colour_bgr.ndim == 2:
        return colour_bgr
    return cv2.cvtColor(colour_bgr, cv2.COLOR_BGR2GRAY)
