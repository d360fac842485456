"""Motive CSV reader and writer (dran_edge.formats.motive) on hand-checked fixtures (tests/data/motive)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dran_edge.formats import motive, motive_write
from dran_edge.errors import InputError

DATA = Path(__file__).parent / "data" / "motive"
R_C = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # Y-up -> Z-up, written out independently


def _expected_dingo1_frame3():
    R_y = Rotation.from_euler("XYZ", [10, -20, 35], degrees=True).as_matrix()
    p_y = np.array([1.02, 0.21, -2.99])
    return R_C @ R_y, R_C @ p_y


@pytest.mark.parametrize("name", ["quaternion_m.csv", "euler_xyz_mm.csv", "euler_zyx_m.csv"])
def test_variants_parse_to_the_same_poses(name):
    take = motive.read_motive_csv(DATA / name)
    assert sorted(take.bodies) == ["box0", "dingo1"]  # markers and rigid-body markers skipped
    np.testing.assert_array_equal(take.frame, [1000, 1001, 1002, 1003])
    np.testing.assert_allclose(take.time_s, [0.0, 0.008333, 0.016667, 0.025])
    d = take.body("dingo1")
    np.testing.assert_array_equal(d.valid, [True, True, False, True])
    assert np.isnan(d.T_world_marker[2]).all()
    # Frame 1000: Motive (1.0, 0.2, -3.0), Y-up -> ours (1.0, 3.0, 0.2), identity rotation.
    np.testing.assert_allclose(d.T_world_marker[0, :3, 3], [1.0, 3.0, 0.2], atol=1e-6)
    np.testing.assert_allclose(d.T_world_marker[0, :3, :3], R_C, atol=1e-6)
    R3, p3 = _expected_dingo1_frame3()
    np.testing.assert_allclose(d.T_world_marker[3, :3, :3], R3, atol=1e-5)
    np.testing.assert_allclose(d.T_world_marker[3, :3, 3], p3, atol=1e-6)
    np.testing.assert_allclose(d.mean_marker_error_m[d.valid], 0.00021, atol=1e-9)
    b = take.body("box0")
    np.testing.assert_array_equal(b.valid, [True, False, True, True])
    assert d.body_id == "1" and b.body_id == "2"


def test_yaw_about_motive_up_is_yaw_about_our_up():
    # Frame 1001: dingo1 turned +30 deg about Motive's vertical Y. In our Z-up world the
    # rigid body's vertical (its Y axis) points along +z and its x axis turned +30 deg about z
    # from world x.
    d = motive.read_motive_csv(DATA / "quaternion_m.csv").body("dingo1")
    R = d.T_world_marker[1, :3, :3]
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-6)
    a = np.radians(30.0)
    # Ry(+30) in Motive sends x to (cos, 0, -sin); in Z-up that is (cos, sin, 0): +30 deg yaw.
    np.testing.assert_allclose(R @ [1, 0, 0], [np.cos(a), np.sin(a), 0], atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)


def test_up_axis_z_keeps_coordinates():
    take = motive.read_motive_csv(DATA / "quaternion_m.csv", up_axis="z")
    np.testing.assert_allclose(take.body("dingo1").T_world_marker[0, :3, 3], [1.0, 0.2, -3.0])


def test_header_metadata():
    take = motive.read_motive_csv(DATA / "euler_xyz_mm.csv")
    assert take.format_version == "1.21"
    assert take.rotation_type == "XYZ" and take.length_units == "Millimeters"
    assert take.capture_frame_rate_hz == 120.0 and take.take_name == "fixture"
    assert take.capture_start_time == "2026-11-20 03.04.05.678 PM"


def test_missing_body_lists_the_available_names():
    take = motive.read_motive_csv(DATA / "quaternion_m.csv")
    with pytest.raises(InputError, match=r"no rigid body named 'dingo7'.*box0, dingo1"):
        take.body("dingo7")


def _edit(tmp_path, line_no: int, old: str, new: str, name="quaternion_m.csv") -> Path:
    lines = (DATA / name).read_text().splitlines()
    assert old in lines[line_no - 1]
    lines[line_no - 1] = lines[line_no - 1].replace(old, new, 1)
    out = tmp_path / "edited.csv"
    out.write_text("\n".join(lines) + "\n")
    return out


def test_malformed_cell_names_its_line(tmp_path):
    p = _edit(tmp_path, 9, "1.010000", "1.0x0000")
    with pytest.raises(InputError, match=r"edited.csv:9: .*dingo1.*'1.0x0000'"):
        motive.read_motive_csv(p)


def test_truncated_row_names_its_line(tmp_path):
    lines = (DATA / "quaternion_m.csv").read_text().splitlines()
    out = tmp_path / "cut.csv"
    out.write_text("\n".join(lines[:-1] + [lines[-1][:40]]) + "\n")
    with pytest.raises(InputError, match=r"cut.csv:11: expected 33 cells"):
        motive.read_motive_csv(out)


def test_partially_blank_body_is_an_error(tmp_path):
    p = _edit(tmp_path, 11, ",1.020000,", ",,")
    with pytest.raises(InputError, match=r":11: .*some rotation/position cells are blank"):
        motive.read_motive_csv(p)


def test_non_unit_quaternion_is_an_error(tmp_path):
    text = (DATA / "quaternion_m.csv").read_text().splitlines()
    cells = text[7].split(",")
    cells[5] = "2.000000"  # W of dingo1 at frame 1000
    text[7] = ",".join(cells)
    out = tmp_path / "q.csv"
    out.write_text("\n".join(text) + "\n")
    with pytest.raises(InputError, match=r"q.csv:8: .*unit quaternion"):
        motive.read_motive_csv(out)


def test_not_a_motive_file(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("Frame,Time\n0,0.0\n")
    with pytest.raises(InputError, match=r"x.csv:1: expected a Motive CSV"):
        motive.read_motive_csv(p)


@pytest.mark.parametrize(
    "old,new,msg",
    [
        ("Rotation Type,Quaternion", "Rotation Type,Matrix", "Rotation Type"),
        ("Length Units,Meters", "Length Units,Furlongs", "Length Units"),
        ("Format Version,1.23", "Format Version,1.1", "format version 1.2x"),
        ("Coordinate Space,Global", "Coordinate Space,Local", "Coordinate Space"),
    ],
)
def test_bad_header_values(tmp_path, old, new, msg):
    p = _edit(tmp_path, 1, old, new)
    with pytest.raises(InputError, match=rf"edited.csv:1: .*{msg}"):
        motive.read_motive_csv(p)


def test_time_going_backwards(tmp_path):
    p = _edit(tmp_path, 10, "0.016667", "0.001000")
    with pytest.raises(InputError, match=r":10: expected increasing times"):
        motive.read_motive_csv(p)


def test_no_header_rows(tmp_path):
    lines = (DATA / "quaternion_m.csv").read_text().splitlines()
    p = tmp_path / "nohdr.csv"
    p.write_text("\n".join(lines[:1] + lines[7:]) + "\n")
    with pytest.raises(InputError, match="header rows"):
        motive.read_motive_csv(p)


def _random_poses(rng, n):
    R = Rotation.random(n, random_state=rng).as_matrix()
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = rng.uniform(-5, 5, (n, 3))
    return T


@pytest.mark.parametrize("rotation_type", ["Quaternion", "XYZ", "ZYX", "YZX"])
@pytest.mark.parametrize("units", ["Meters", "Millimeters"])
def test_writer_round_trip(tmp_path, rotation_type, units):
    rng = np.random.default_rng(7)
    n = 25
    t = np.arange(n) / 120.0
    A, B = _random_poses(rng, n), _random_poses(rng, n)
    A[[3, 4, 10]] = np.nan
    take = motive_write.make_take(t, {"dingo1": A, "box0": B}, take_name="sim")
    p = tmp_path / "gt.csv"
    motive_write.write_motive_csv(p, take, rotation_type=rotation_type, length_units=units)
    raw = p.read_bytes()
    assert raw.count(b"\r\n") == n + 7
    back = motive.read_motive_csv(p)
    assert list(back.bodies) == ["dingo1", "box0"] and back.take_name == "sim"
    a = back.body("dingo1")
    np.testing.assert_array_equal(a.valid, ~np.isnan(A[:, 0, 0]))
    np.testing.assert_allclose(back.time_s, np.round(t, 6))
    tol_p = 1e-6 if units == "Meters" else 1e-9
    np.testing.assert_allclose(a.T_world_marker[a.valid, :3, 3], A[a.valid, :3, 3], atol=tol_p)
    np.testing.assert_allclose(a.T_world_marker[a.valid, :3, :3], A[a.valid, :3, :3], atol=1e-5)
    np.testing.assert_allclose(back.body("box0").T_world_marker, B, atol=1e-5)


def test_writer_header_rows_as_motive_writes_them(tmp_path):
    T = np.tile(np.eye(4), (2, 1, 1))
    T[:, :3, 3] = [1.0, 3.0, 0.2]  # ours (Z-up) -> Motive (1.0, 0.2, -3.0)
    T[:, :3, :3] = R_C  # a rigid body whose axes are Motive's world axes: identity in the file
    take = motive_write.make_take([0.0, 1 / 120], {"dingo1": T}, take_name="run01")
    p = tmp_path / "gt.csv"
    motive_write.write_motive_csv(p, take)
    lines = p.read_text().splitlines()
    assert lines[0].startswith(
        "Format Version,1.23,Take Name,run01,Take Notes,,Capture Frame "
        "Rate,120.000000,Export Frame Rate,120.000000,Capture Start Time,"
    )
    assert lines[0].endswith(
        ",Rotation Type,Quaternion,Length Units,Meters,Coordinate Space,Global"
    )
    assert lines[1] == ""
    assert lines[2] == ",Type" + ",Rigid Body" * 8
    assert lines[3] == ",Name" + ",dingo1" * 8
    assert lines[4] == ",ID" + ",1" * 8
    assert lines[5] == ",," + "Rotation," * 4 + "Position," * 3 + "Mean Marker Error"
    assert lines[6] == "Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,"
    assert lines[7] == (
        "0,0.000000,0.000000,0.000000,0.000000,1.000000,1.000000,0.200000,-3.000000,0.000000"
    )
