"""Frame byte layout, frame sources (files, frames folder, RealSense recording, forwarded, OAK,
live RealSense behind the hardware marker), the ``detect`` command and the layering rule."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

cv2 = pytest.importorskip("cv2")

from dran_edge.perception.frame import FRAME_HEADER, Frame, frame_from_bytes, frame_to_bytes  # noqa: E402
from dran_edge.perception.sources import (  # noqa: E402
    ForwardedFramesSource,
    ImageFilesSource,
    RecordedFramesSource,
    open_source,
    write_recorded_frames,
)

from dran_edge import geometry as geo  # noqa: E402
from dran_edge.errors import DecodeError, InputError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "apriltag"
K = np.array([[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]])


def small_frame(stamp_ns=1_700_000_000_123_456_789, depth=True, h=6, w=8):
    rng = np.random.default_rng(stamp_ns % 1000)
    colour = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    d = rng.integers(0, 65536, (h, w), dtype=np.uint16) if depth else None
    return Frame(stamp_ns, colour, d, "dingo1/color")


# --------------------------------------------------------------------------- byte layout
@pytest.mark.parametrize("codec", ["raw", "png"])
def test_frame_bytes_round_trip_lossless(codec):
    f = small_frame()
    g = frame_from_bytes(frame_to_bytes(f, colour_codec=codec, depth_codec=codec))
    assert g.stamp_ns == f.stamp_ns and g.camera_id == f.camera_id
    assert np.array_equal(g.colour, f.colour) and np.array_equal(g.depth, f.depth)


def test_frame_bytes_jpeg_and_no_depth():
    f = small_frame(depth=False, h=32, w=32)
    g = frame_from_bytes(frame_to_bytes(f, colour_codec="jpeg"))
    assert g.depth is None and g.colour.shape == (32, 32, 3)


def test_frame_header_golden_bytes():
    f = Frame(5, np.zeros((1, 2, 3), np.uint8), np.array([[1, 258]], np.uint16), "c")
    data = frame_to_bytes(f, colour_codec="raw", depth_codec="raw")
    assert data == (
        b"DRFR\x01\x01\x00\x00"
        + (5).to_bytes(8, "little")
        + b"\x02\x00\x01\x00"
        + (6).to_bytes(4, "little")
        + (4).to_bytes(4, "little")
        + b"\x01"
        + b"c"
        + bytes(6)
        + b"\x01\x00\x02\x01"
    )
    assert FRAME_HEADER.size == 29


def test_rgb_flag_swaps_to_bgr():
    f = small_frame(depth=False)
    data = bytearray(frame_to_bytes(f, colour_codec="raw"))
    data[5] |= 2
    assert np.array_equal(frame_from_bytes(bytes(data)).colour, f.colour[..., ::-1])


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda b: b[:10], "header bytes"),
        (lambda b: b"XXXX" + b[4:], "magic"),
        (lambda b: b[:4] + b"\x02" + b[5:], "version"),
        (lambda b: b + b"\x00", "in all"),
        (lambda b: b[:-1], "in all"),
        (lambda b: b[:16] + (0).to_bytes(2, "little") + b[18:], "px sides"),
    ],
)
def test_frame_decode_is_strict(mutate, message):
    data = frame_to_bytes(small_frame(), colour_codec="raw", depth_codec="raw")
    with pytest.raises(DecodeError, match=message):
        frame_from_bytes(mutate(data))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200), st.integers(0, 60))
def test_frame_decode_never_fails_otherwise(junk, cut):
    """Any byte string decodes to a frame or raises DecodeError, nothing else."""
    good = frame_to_bytes(small_frame(), colour_codec="raw", depth_codec="raw")
    for data in (junk, good[:cut] + junk, good[:29] + junk):
        try:
            frame_from_bytes(data)
        except DecodeError:
            pass


def test_forwarded_source_drops_bad_records():
    good = [frame_to_bytes(small_frame(stamp_ns=s)) for s in (1, 2, 3)]
    src = ForwardedFramesSource([good[0], b"junk", good[1], good[2][:-3], good[2]])
    assert [f.stamp_ns for f in src] == [1, 2, 3]
    assert src.dropped == 2
    queue = list(good)
    assert [f.stamp_ns for f in ForwardedFramesSource(lambda: queue.pop(0) if queue else None)] == [
        1,
        2,
        3,
    ]


# --------------------------------------------------------------------------- files
def test_recorded_frames_round_trip(tmp_path):
    frames = [small_frame(stamp_ns=s, depth=(s != 20)) for s in (10, 20, 30)]
    assert write_recorded_frames(tmp_path / "frames", frames) == 3
    src = open_source(str(tmp_path / "frames"))
    assert isinstance(src, RecordedFramesSource)
    back = list(src)
    assert [f.stamp_ns for f in back] == [10, 20, 30]
    assert back[1].depth is None
    for a, b in zip(frames, back):
        assert np.array_equal(a.colour, b.colour)
        assert (a.depth is None) or np.array_equal(a.depth, b.depth)


def test_recorded_frames_strict_csv(tmp_path):
    folder = tmp_path / "f"
    write_recorded_frames(folder, [small_frame(stamp_ns=s) for s in (10, 20)])
    text = (folder / "frames.csv").read_text().splitlines()
    (folder / "frames.csv").write_text("\n".join([text[0], text[2], text[1]]) + "\n")
    with pytest.raises(InputError, match=r"frames\.csv:3: stamp_ns must increase"):
        RecordedFramesSource(folder)


def test_image_files_source():
    src = open_source(str(DATA))
    assert isinstance(src, ImageFilesSource)
    frames = list(src)
    assert len(frames) == 4 and [f.stamp_ns for f in frames] == [0, 1, 2, 3]
    with pytest.raises(InputError, match="no such file"):
        open_source(str(DATA / "missing.png"))


# --------------------------------------------------------------------------- RealSense
def test_realsense_recording_written_and_played_back_through_pyrealsense2(tmp_path):
    rs = pytest.importorskip("pyrealsense2", exc_type=ImportError)
    del rs
    from dran_edge.perception.render import TagRenderer, write_realsense_recording
    from dran_edge.perception.sources import RealSenseRecordingSource

    renderer = TagRenderer()
    frames = []
    for i in range(6):
        T = geo.se3_from_rt(np.diag([-1.0, -1, 1]), [0.02 * i, 0.0, 1.0 + 0.05 * i])
        colour, depth = renderer.render(K, 640, 480, [T], [i], 0.16)
        frames.append(Frame(1_700_000_000_000_000_000 + i * 33_333_333, colour, depth, "sw"))
    path = tmp_path / "capture.db3"
    assert write_realsense_recording(path, frames, K) == 6
    src = open_source(str(path))
    assert isinstance(src, RealSenseRecordingSource)
    back = list(src)
    assert len(back) == 6
    for a, b in zip(frames, back):
        # stamps travel as float64 milliseconds: ~0.1 us resolution at epoch scale
        assert abs(a.stamp_ns - b.stamp_ns) < 1000
        assert np.array_equal(a.colour, b.colour)
        assert b.depth is not None and np.abs(a.depth.astype(int) - b.depth).max() <= 1


def test_realsense_recording_missing_file(tmp_path):
    pytest.importorskip("pyrealsense2", exc_type=ImportError)
    from dran_edge.perception.sources import RealSenseRecordingSource

    with pytest.raises(InputError, match="no such recording"):
        RealSenseRecordingSource(tmp_path / "none.db3")


@pytest.mark.hardware
def test_live_realsense_frames_and_stamps():
    rs = pytest.importorskip("pyrealsense2", exc_type=ImportError)
    if len(rs.context().query_devices()) == 0:
        pytest.skip("no RealSense device connected")
    from dran_edge.perception.sources import RealSenseSource

    src = RealSenseSource(max_reconnects=2)
    frames = []
    for f in src:
        frames.append(f)
        if len(frames) == 30:
            break
    src.close()
    assert all(f.colour.shape == (480, 640, 3) and f.depth is not None for f in frames)
    stamps = np.array([f.stamp_ns for f in frames])
    assert np.all(np.diff(stamps) > 0)


@pytest.mark.hardware
def test_live_realsense_reconnects_after_hardware_reset():
    """A hardware reset drops the device off USB like an unplug; iteration must resume."""
    rs = pytest.importorskip("pyrealsense2", exc_type=ImportError)
    if len(rs.context().query_devices()) == 0:
        pytest.skip("no RealSense device connected")
    from dran_edge.perception.sources import RealSenseSource

    src = RealSenseSource(timeout_ms=1000, reconnect_s=1.0, max_reconnects=20)
    n_after = 0
    for i, _ in enumerate(src):
        if i == 10:
            src._pipe.get_active_profile().get_device().hardware_reset()
        if src.reconnects:
            n_after += 1
            if n_after == 10:
                break
    src.close()
    assert src.reconnects >= 1 and n_after == 10


def test_depthai_source_skips_cleanly_without_depthai():
    try:
        import depthai  # noqa: F401
    except ImportError:
        from dran_edge.perception.sources import DepthAISource

        from dran_edge.errors import DependencyError

        with pytest.raises(DependencyError, match="depthai"):
            DepthAISource()
        pytest.skip("depthai not installed (the 'oak' extra): constructor error checked")
    pytest.skip("depthai installed but no OAK test without hardware")


# --------------------------------------------------------------------------- CLI, layering
def test_detect_command_json_lines(capsys):
    pytest.importorskip("pupil_apriltags")
    from dran_edge.cli.app import main

    assert (
        main(
            [
                "detect",
                str(DATA),
                "--json",
                "--intrinsics",
                "615,615,319.5,239.5",
                "--tag-size",
                "0.16",
            ]
        )
        == 0
    )
    out, err = capsys.readouterr()
    recs = [json.loads(line) for line in out.splitlines()]
    expected = json.loads((DATA / "expected.json").read_text())["images"]
    assert len(recs) == 7
    for r in recs:
        assert set(r) >= {"tag_id", "corners", "hamming", "decision_margin", "T_camera_tag"}
        e = next(t for t in expected[r["camera_id"]] if t["tag_id"] == r["tag_id"])
        assert np.abs(np.asarray(r["corners"]) - e["corners"]).max() < 0.5
        if r["accepted"]:
            assert (
                np.abs(
                    np.asarray(r["T_camera_tag"])[:3, 3] - np.asarray(e["T_camera_tag"])[:3, 3]
                ).max()
                < 0.05
            )
    assert '"frames": 4' in err


def test_detect_command_with_calib_gives_object_ids(tmp_path, capsys):
    pytest.importorskip("pupil_apriltags")
    from dran_edge.cli.app import main

    assert (
        main(
            [
                "detect",
                str(DATA / "three_tags_clutter.png"),
                "--json",
                "--calib",
                str(ROOT / "calib"),
                "--robot",
                "dingo1",
            ]
        )
        == 0
    )
    recs = [json.loads(line) for line in capsys.readouterr()[0].splitlines()]
    by_tag = {r["tag_id"]: r for r in recs}
    assert by_tag[12]["object_id"] == 3 and by_tag[13]["object_id"] == 3
    assert "object_id" not in by_tag[42] and by_tag[42]["reject"] == "unknown_tag"
    assert "T_body_object" in by_tag[12]


def test_perception_imports_no_hardware_library():
    code = (
        "import sys; import dran_edge.perception.pipeline, dran_edge.perception.sources, "
        "dran_edge.perception.render, dran_edge.cli.commands.detect; "
        "bad = [m for m in ('pyrealsense2', 'depthai', 'zmq') if m in sys.modules]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
