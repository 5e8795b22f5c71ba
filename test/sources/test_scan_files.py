"""Readers for the shared data: PCD, VTK, odometry CSV, and the PointCloud2-like builder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mfp_mapper.sensing import pointcloud as pc
from mfp_mapper.sensing.deskew import cloud_to_map
from mfp_mapper.sensing.pointcloud import parse_pointcloud2
from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer, quaternion_to_matrix
from mfp_mapper.sources.pose_files import read_odometry_csv
from mfp_mapper.sources.scan_files import (
    DatasetFormatError,
    cloud_message,
    cloud_message_from_columns,
    list_vtk_scans,
    read_pcd,
    read_vtk_points,
)

PCD_HEADER = """# .PCD v0.7 - Point Cloud Data file format
VERSION 0.7
FIELDS {fields}
SIZE {sizes}
TYPE {types}
COUNT {counts}
WIDTH {n}
HEIGHT 1
VIEWPOINT 0 0 0 1 0 0 0
POINTS {n}
DATA {data}
"""


def pcd_header(n: int, data: str = "binary", **overrides: str) -> bytes:
    values = {"fields": "x y z ring", "sizes": "4 4 4 2", "types": "F F F U", "counts": "1 1 1 1"}
    return PCD_HEADER.format(n=n, data=data, **(values | overrides)).encode()


def pcd_header_value(path: Path, key: str) -> str:
    with path.open("rb") as stream:
        for line in stream:
            if line.startswith(key.encode() + b" "):
                return line.decode().split(maxsplit=1)[1].strip()
    raise AssertionError(f"{path} has no {key}")


# --- PCD -----------------------------------------------------------------------------------


def test_read_every_nebula_pcd(shared_data: Path) -> None:
    paths = sorted((shared_data / "nebula_frames").glob("*.pcd"))
    assert len(paths) == 12
    for path in paths:
        columns = read_pcd(path)
        points = int(pcd_header_value(path, "POINTS"))
        assert list(columns) == pcd_header_value(path, "FIELDS").split()
        assert all(len(column) == points for column in columns.values())
        assert all(columns[axis].dtype == np.float32 for axis in "xyz")
        xyz = np.stack([columns[a] for a in "xyz"], axis=1)
        assert np.isfinite(xyz).all(axis=1).mean() > 0.5, path.name
        if "time_stamp" in columns:
            assert columns["time_stamp"].dtype == np.uint32
            assert columns["intensity"].dtype == np.uint8
            assert columns["channel"].dtype == np.uint16


def test_read_binary_pcd_round_trip(tmp_path: Path) -> None:
    records = np.zeros(5, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "<u2")])
    records["x"] = np.arange(5)
    records["ring"] = [3, 1, 4, 1, 5]
    path = tmp_path / "cloud.pcd"
    path.write_bytes(pcd_header(5) + records.tobytes())
    columns = read_pcd(path)
    np.testing.assert_array_equal(columns["x"], np.arange(5, dtype=np.float32))
    np.testing.assert_array_equal(columns["ring"], [3, 1, 4, 1, 5])
    assert columns["ring"].dtype == np.uint16


def test_read_ascii_pcd_with_count_and_padding(tmp_path: Path) -> None:
    header = pcd_header(
        2,
        "ascii",
        fields="x y z _ normal",
        sizes="4 4 4 1 8",
        types="F F F U F",
        counts="1 1 1 1 3",
    )
    path = tmp_path / "ascii.pcd"
    path.write_bytes(header + b"1 2 3 0 0.1 0.2 0.3\n4 5 nan 0 1 2 3\n")
    columns = read_pcd(path)
    assert list(columns) == ["x", "y", "z", "normal"]
    np.testing.assert_array_equal(columns["y"], [2.0, 5.0])
    assert np.isnan(columns["z"][1])
    assert columns["normal"].shape == (2, 3) and columns["normal"].dtype == np.float64


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"VERSION 0.7\nFIELDS x\n", "no DATA line"),
        (pcd_header(5) + b"\x00" * 10, r"truncated, 10 bytes of data for 5 points of 14 bytes"),
        (pcd_header(1, types="F F F Q"), "field 'ring' has unsupported TYPE Q SIZE 2"),
        (pcd_header(1, sizes="4 4 4"), "need one entry per field, got 4, 3, 4, 4"),
        (pcd_header(1, data="binary_compressed"), "DATA 'binary_compressed' is not supported"),
        (pcd_header(2, data="ascii") + b"1 2 3 4\n", "4 ascii values, expected 2 points x 4"),
        (pcd_header(1, data="ascii") + b"1 2 three 4\n", "non-numeric ascii data"),
        (pcd_header(1).replace(b"POINTS 1", b"POINTS many"), "needs an integer POINTS line"),
        (pcd_header(1).replace(b"TYPE", b"KIND"), "no TYPE line"),
    ],
    ids=[
        "no_data",
        "truncated",
        "type",
        "sizes",
        "compressed",
        "ascii_count",
        "ascii_text",
        "points",
        "no_type",
    ],
)
def test_malformed_pcd(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.pcd"
    path.write_bytes(content)
    with pytest.raises(DatasetFormatError, match=message):
        read_pcd(path)


# --- VTK -----------------------------------------------------------------------------------


def test_read_every_norlab_scan(shared_data: Path) -> None:
    scans = list_vtk_scans(shared_data / "norlab_sequence" / "scans")
    assert len(scans) == 14
    stamps = [stamp for stamp, _ in scans]
    assert stamps == sorted(stamps) and np.all(np.diff(stamps) == pytest.approx(0.1, abs=0.01))
    for _, path in scans:
        points = read_vtk_points(path)
        count = int(pcd_header_value(path, "POINTS").split()[0])
        assert points.shape == (count, 3) and 40_000 < count < 43_000
        assert np.isfinite(points).all()
        first = [float(v) for v in path.read_text().splitlines()[5].split()]
        np.testing.assert_array_equal(points[0], first)


def test_scan_stamps_use_unpadded_nanoseconds(tmp_path: Path) -> None:
    for name in ["cloud_10_185535488.vtk", "cloud_10_85582848.vtk", "notes.vtk"]:
        (tmp_path / name).write_text("")
    scans = list_vtk_scans(tmp_path)
    assert [path.name for _, path in scans] == ["cloud_10_85582848.vtk", "cloud_10_185535488.vtk"]
    assert scans[0][0] == pytest.approx(10.085582848)


VTK_HEAD = "# vtk DataFile Version 3.0\ntest\nASCII\nDATASET POLYDATA\n"


def test_read_vtk_points_spanning_lines(tmp_path: Path) -> None:
    path = tmp_path / "cloud.vtk"
    path.write_text(VTK_HEAD + "POINTS 3 float\n1 2 3 4\n5 6\n7 8 9\nVERTICES 3 6\n")
    np.testing.assert_array_equal(read_vtk_points(path), np.arange(1, 10).reshape(3, 3))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("hello\n", "not a legacy VTK file"),
        (VTK_HEAD.replace("ASCII", "BINARY") + "POINTS 1 float\n", "only ASCII VTK"),
        (VTK_HEAD.replace("POLYDATA", "UNSTRUCTURED_GRID") + "POINTS 1 float\n", "POLYDATA"),
        (VTK_HEAD + "VERTICES 1 2\n", "no POINTS section"),
        (VTK_HEAD + "POINTS 2 float\n1 2 3\n", "POINTS 2 but only 3 values"),
        (VTK_HEAD + "POINTS 1 float\n1 two 3\n", "non-numeric POINTS data"),
        (VTK_HEAD + "POINTS x float\n1 2 3\n", "bad POINTS line"),
    ],
    ids=["magic", "binary", "dataset", "no_points", "truncated", "text", "count"],
)
def test_malformed_vtk(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "bad.vtk"
    path.write_text(content)
    with pytest.raises(DatasetFormatError, match=message):
        read_vtk_points(path)


# --- odometry CSV ----------------------------------------------------------------------------


def test_read_odometry_csv(shared_data: Path) -> None:
    odometry = read_odometry_csv(shared_data / "norlab_sequence" / "icp_odom.csv")
    assert len(odometry) == 14
    assert odometry["stamp"][0] == pytest.approx(1690309709.2853056, abs=1e-7)
    np.testing.assert_allclose(
        odometry["position"][0], [0.8582466244697571, -0.1377161741256714, 0.03212672472000122]
    )
    assert odometry["quaternion"][0][3] == pytest.approx(0.9951240157472429)
    np.testing.assert_allclose(np.linalg.norm(odometry["quaternion"], axis=1), 1.0, atol=1e-6)
    assert np.all(np.diff(odometry["stamp"]) > 0)


def test_odometry_csv_errors(tmp_path: Path) -> None:
    path = tmp_path / "odom.csv"
    path.write_text("header.stamp.sec,header.stamp.nanosec,pose.pose.position.x\n1,2,3\n")
    with pytest.raises(
        DatasetFormatError, match=r"missing odometry columns pose\.pose\.position\.y"
    ):
        read_odometry_csv(path)
    columns = "header.stamp.sec,header.stamp.nanosec," + ",".join(
        [f"pose.pose.position.{a}" for a in "xyz"] + [f"pose.pose.orientation.{a}" for a in "xyzw"]
    )
    path.write_text(f"{columns}\n1,0,0,0,0,0,0,0,1\n2,0,0,zero,0,0,0,0,1\n")
    with pytest.raises(DatasetFormatError, match=r"odom\.csv:3: bad odometry value"):
        read_odometry_csv(path)


def test_norlab_scans_reach_the_map_through_the_odometry(shared_data: Path) -> None:
    sequence = shared_data / "norlab_sequence"
    odometry = read_odometry_csv(sequence / "icp_odom.csv")
    buffer = PoseBuffer()
    for row in odometry:
        assert buffer.add(row["stamp"], row["position"], row["quaternion"])
    stamp, path = list_vtk_scans(sequence / "scans")[5]
    xyz = read_vtk_points(path)
    columns = {axis: xyz[:, k].astype(np.float32) for k, axis in enumerate("xyz")}
    cloud = parse_pointcloud2(cloud_message_from_columns(columns, stamp))
    points, origin = cloud_to_map(cloud, stamp, buffer, Extrinsic())
    row = odometry[5]
    expected = (
        cloud.xyz @ quaternion_to_matrix(row["quaternion"] / np.linalg.norm(row["quaternion"])).T
    )
    np.testing.assert_allclose(points, expected + row["position"], atol=1e-9)
    np.testing.assert_allclose(origin, row["position"])


# --- PointCloud2-like messages -----------------------------------------------------------------


def test_cloud_message_layout_from_records() -> None:
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "t"],
            "formats": [">f4", ">f4", ">f4", ">u4"],
            "offsets": [0, 4, 8, 16],
            "itemsize": 24,
        }
    )
    msg = cloud_message(np.zeros((2, 3), dtype=dtype), stamp=12.75, frame_id="os_lidar")
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (2, 3, 24, 72)
    assert msg.is_bigendian and len(msg.data) == 144
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields][3] == (
        "t",
        16,
        pc.UINT32,
        1,
    )
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (
        12,
        750_000_000,
        "os_lidar",
    )


def test_cloud_message_rejects_what_pointcloud2_cannot_hold() -> None:
    with pytest.raises(ValueError, match="mix byte orders"):
        cloud_message(np.zeros(2, dtype=[("x", "<f4"), ("y", ">f4"), ("z", "<f4")]))
    with pytest.raises(ValueError, match="no PointField datatype"):
        cloud_message(np.zeros(2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("v", "?")]))
    with pytest.raises(ValueError, match="structured array"):
        cloud_message(np.zeros(2))
