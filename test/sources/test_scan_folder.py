"""Scan files (PLY, KITTI .bin, VTK, PCD) and scan folders: order, stamps, per-point time;
a folder as a recording (``open_folder``): its poses and the errors that stop it."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
from folder_helpers import write_pcd, write_ply

from mfp_mapper.cli.input_args import input_options, parse_bound
from mfp_mapper.config.replay_options import ReplayError, ReplayOptions
from mfp_mapper.config.schema import xyz_rpy
from mfp_mapper.sensing import pipeline
from mfp_mapper.sources.scan_files import DatasetFormatError, read_kitti_bin, read_ply
from mfp_mapper.sources.scan_folder import is_scan_folder, open_folder, open_scan_folder

COLUMNS = {
    "x": np.array([1.0, 2.5, -3.0], "<f4"),
    "y": np.array([0.5, -1.0, 4.0], "<f4"),
    "z": np.array([0.0, 0.25, 1.0], "<f4"),
    "intensity": np.array([10, 20, 30], "u1"),
    "time": np.array([0.0, 0.05, 0.099], "<f8"),
}


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path: Path, binary: bool) -> None:
    path = tmp_path / "a.ply"
    write_ply(path, COLUMNS, binary=binary)
    columns = read_ply(path)
    assert list(columns) == list(COLUMNS)
    for name, values in COLUMNS.items():
        np.testing.assert_array_equal(columns[name], values)
        assert columns[name].dtype == values.dtype.newbyteorder("<")


def test_bad_ply(tmp_path: Path) -> None:
    path = tmp_path / "b.ply"
    header = "ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\nend_header\n"
    path.write_bytes(header.encode() + np.array([1.5, -2.0], dtype=">f4").tobytes())
    big = read_ply(path)  # big-endian (plyfile): native values
    assert big["x"].tolist() == [1.5, -2.0] and big["x"].dtype == np.dtype("=f4")
    path.write_bytes(header.encode() + b"\x00\x01")
    with pytest.raises(DatasetFormatError, match="b.ply: not a readable PLY file"):
        read_ply(path)
    write_ply(path, COLUMNS)
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(DatasetFormatError, match="not a readable PLY file"):
        read_ply(path)
    path.write_bytes(b"ply\nformat ascii 1.0\nelement face 1\nproperty float a\nend_header\n1\n")
    with pytest.raises(DatasetFormatError, match="no vertex element"):
        read_ply(path)


def test_kitti_bin(tmp_path: Path) -> None:
    records = np.arange(12, dtype="<f4").reshape(3, 4)
    records.tofile(tmp_path / "000000.bin")
    columns = read_kitti_bin(tmp_path / "000000.bin")
    np.testing.assert_array_equal(columns["x"], records[:, 0])
    np.testing.assert_array_equal(columns["intensity"], records[:, 3])
    (tmp_path / "bad.bin").write_bytes(b"\0" * 20)
    with pytest.raises(DatasetFormatError, match="16-byte"):
        read_kitti_bin(tmp_path / "bad.bin")


def test_folder_order_and_stamps(tmp_path: Path) -> None:
    for name in ("10.pcd", "2.pcd", "1.pcd"):
        write_pcd(tmp_path / name, COLUMNS)
    folder = open_scan_folder(tmp_path)
    assert [s.path.name for s in folder.scans] == ["1.pcd", "2.pcd", "10.pcd"]  # natural order
    assert [s.stamp for s in folder.scans] == pytest.approx([0.0, 0.1, 0.2])
    assert folder.stamp_source.startswith("none")
    (tmp_path / "times.txt").write_text("5.0\n5.1 extra\n5.3\n")
    folder = open_scan_folder(tmp_path)
    assert [s.stamp for s in folder.scans] == [5.0, 5.1, 5.3]
    (tmp_path / "times.txt").write_text("5.0\n")
    with pytest.raises(DatasetFormatError, match="1 stamps for 3 scan files"):
        open_scan_folder(tmp_path)


def test_stamps_from_names(tmp_path: Path) -> None:
    names = ["cloud_1700000000_900000000.pcd", "cloud_1700000001_50000000.pcd"]
    for name in names:  # nanoseconds not zero-padded: name order is not time order
        write_pcd(tmp_path / name, COLUMNS)
    folder = open_scan_folder(tmp_path)
    assert [s.stamp for s in folder.scans] == pytest.approx([1700000000.9, 1700000001.05])
    other = tmp_path / "ns"
    other.mkdir()
    write_pcd(other / "vlp16_1673400149711850138.pcd", COLUMNS)
    write_pcd(other / "1673400149.25.pcd", COLUMNS)
    stamps = [s.stamp for s in open_scan_folder(other).scans]
    assert stamps == pytest.approx([1673400149.25, 1673400149.711850138])


def test_folder_errors(tmp_path: Path) -> None:
    write_pcd(tmp_path / "a.pcd", COLUMNS)
    write_ply(tmp_path / "b.ply", COLUMNS)
    with pytest.raises(DatasetFormatError, match="several scan kinds"):
        open_scan_folder(tmp_path)
    assert is_scan_folder(tmp_path) and not is_scan_folder(tmp_path / "a.pcd")


def test_per_point_time_reaches_the_pipeline(shared_data: Path) -> None:
    """Nebula's Velodyne frame carries time_stamp (u32 ns): the parsed cloud has offsets."""
    folder = open_scan_folder(shared_data / "nebula_frames")
    vlp16 = next(k for k, s in enumerate(folder.scans) if "vlp16" in s.path.name.lower())
    cloud = pipeline.parse_scan(folder.message(vlp16))
    assert cloud.time_offset is not None
    assert 0.0 <= cloud.time_offset.min() < cloud.time_offset.max() < 0.2  # ns -> s
    others = [k for k, s in enumerate(folder.scans) if "hesai" in s.path.name.lower()]
    assert pipeline.parse_scan(folder.message(others[0])).time_offset is None


def test_start_end_syntax() -> None:
    assert parse_bound("12.5") == ("offset", 12.5)
    assert parse_bound("@1700000012.5") == ("stamp", 1700000012.5)
    assert parse_bound("#40") == ("index", 40)
    for bad in ("#-1", "x", "@", "#1.5"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_bound(bad)
    args = argparse.Namespace(start=("index", 3), end=("stamp", 9.0), odometry=None)
    assert input_options(args) == {"start_index": 3, "end": 9.0}


def _three_scans(folder: Path) -> Path:
    folder.mkdir()
    for k in range(3):
        write_pcd(
            folder / f"{k}.pcd",
            {"x": np.ones(3, "<f4"), "y": np.zeros(3, "<f4"), "z": np.zeros(3, "<f4")},
        )
    return folder


def test_a_folder_as_a_recording(tmp_path: Path) -> None:
    folder = _three_scans(tmp_path / "scans")
    (tmp_path / "scans" / "3.pcd").mkdir()  # named like a scan, not a file: skipped, said
    kitti = tmp_path / "poses.txt"
    kitti.write_text("".join(f"1 0 0 {k} 0 1 0 0 0 0 1 0\n" for k in range(3)))
    said: list[str] = []
    with open_folder(folder, ReplayOptions(), kitti, log=said.append) as recording:
        assert recording.name == str(folder) and recording.cloud_count == 3
        assert recording.cloud_source.startswith("3 .pcd files (stamps: none found")
        assert recording.map_frame == "world" and recording.cloud_frame == "lidar"
        assert recording.extrinsic_source == "identity (poses are the lidar's)"
        clouds = list(recording.clouds())
        assert [c.position for c in clouds] == [0, 1, 2]
        assert pipeline.scan_stamp(clouds[2].load()) == pytest.approx(0.2)
        np.testing.assert_allclose(recording.pose_source.interpolate([0.2])[0], [[2, 0, 0]])
    assert said and "skipped 1 entries" in said[0] and "3.pcd (a folder)" in said[0]
    given = ReplayOptions.of(extrinsic=xyz_rpy([0, 0, 1], [0, 0, 0]))
    with open_folder(folder, given, "identity") as recording:
        assert recording.map_frame == "lidar" and recording.poses.source == "identity"
        assert recording.extrinsic_source == "given on the command line"
        np.testing.assert_allclose(recording.extrinsic_of("lidar").translation, [0, 0, 1])


def test_folder_recording_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ReplayError, match="no scan files"):
        open_folder(empty, ReplayOptions(), "identity")
    folder = _three_scans(tmp_path / "scans")
    with pytest.raises(ReplayError, match="needs poses"):
        open_folder(folder, ReplayOptions())
    kitti = tmp_path / "poses.txt"
    kitti.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ReplayError, match="1 KITTI poses for 3 scans"):
        open_folder(folder, ReplayOptions(), kitti)
    tum = tmp_path / "poses.tum"
    tum.write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")
    with pytest.raises(ReplayError, match="TUM poses are matched by time.*no stamps"):
        open_folder(folder, ReplayOptions(), tum)
    with pytest.raises(ReplayError, match="times file not found"):
        open_folder(folder, ReplayOptions(), tum, tmp_path / "absent.txt")


def test_kiss_icp_missing_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "kiss_icp.config", None)  # import raises ImportError
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(2):
        xyz = {"x": np.full(4, 3.0, "<f4"), "y": np.arange(4, dtype="<f4"), "z": np.zeros(4, "<f4")}
        write_pcd(folder / f"{k}.pcd", xyz)
    with pytest.raises(
        ReplayError, match="needs the Python package kiss-icp: pip install kiss-icp"
    ):
        open_folder(folder, ReplayOptions.of(odometry="kiss-icp"))
