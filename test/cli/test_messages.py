"""What users and disks produce gets one clear line (issue 21): damaged bags, YAML, scan
folders with odd entries, headers and stamps, unusable time fields, degenerate clouds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from folder_helpers import write_pcd, write_ply

from mfp_mapper.cli import main
from mfp_mapper.sources.scan_files import DatasetFormatError, read_pcd

QUIET = ["--resolution", "0.5", "-q"]


def _one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def _cloud(seed: int, n: int = 400) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-8.0, 8.0, (n, 3)).astype("<f4")
    return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}


def test_sqlite_corruption_mid_bag_is_one_line(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    bag = tmp_path / "sq"
    assert main(["simulate", str(bag), "--scene", "small", "--scans", "20",
                 "--format", "sqlite3"]) == 0  # fmt: skip
    db = next(bag.glob("*.db3"))
    raw = bytearray(db.read_bytes())
    raw[len(raw) // 2 : len(raw) // 2 + 8192] = b"\xab" * 8192
    db.write_bytes(bytes(raw))
    capsys.readouterr()
    assert main(["replay", str(bag), "-o", str(tmp_path / "m.npz"), *QUIET]) == 1
    err = _one_error_line(capsys)
    assert "cannot read the bag after" in err and "no map written" in err
    assert not (tmp_path / "m.npz").exists()


def test_yaml_errors_are_one_line_with_the_line(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    bag = tmp_path / "b"
    assert main(["simulate", str(bag), "--scene", "small", "--scans", "2"]) == 0
    bad = tmp_path / "bad.yaml"
    bad.write_text("mfp_mapper:\n  ros__parameters:\n    resolution: [1, 2\n    x: 1\n")
    capsys.readouterr()
    args = ["replay", str(bag), "-o", str(tmp_path / "m.npz"), "--config", str(bad), "-q"]
    assert main(args) == 1
    err = _one_error_line(capsys)
    assert "bad.yaml" in err and "line 4, column 6" in err


def test_skipped_scan_entries_are_named(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(3):
        write_ply(folder / f"{k:06d}.ply", _cloud(k))
    (folder / "000003.ply").symlink_to(tmp_path / "gone.ply")  # dangling
    (folder / "000004.ply").mkdir()
    poses = tmp_path / "poses.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5)  # one per name: 5 for 3 scans
    capsys.readouterr()
    args = ["replay", str(folder), "--poses", str(poses), "-o", str(tmp_path / "m.npz"), *QUIET]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 2  # warning, error
    assert "5 KITTI poses for 3 scans" in err
    assert "000003.ply (a dangling link)" in err and "000004.ply (a folder)" in err
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "skipped 2 entries named like scan files" in err and "000003.ply" in err


def test_nan_stamps_in_times_txt(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(3):
        write_pcd(folder / f"{k:06d}.pcd", _cloud(k))
    (folder / "times.txt").write_text("0.0\nnan\n0.2\n")
    capsys.readouterr()
    args = ["replay", str(folder), "--poses", "identity", "-o", str(tmp_path / "m.npz"), *QUIET]
    assert main(args) == 1
    err = _one_error_line(capsys)
    assert "times.txt: stamp 2 is nan, not a finite number of seconds" in err


def test_pcd_header_counts_are_checked(tmp_path: Path) -> None:
    path = tmp_path / "a.pcd"
    write_pcd(path, _cloud(0, 5))
    good = path.read_bytes()
    path.write_bytes(good.replace(b"POINTS 5", b"POINTS -5"))
    with pytest.raises(DatasetFormatError, match="POINTS -5, a negative count"):
        read_pcd(path)
    path.write_bytes(good.replace(b"POINTS 5", b"POINTS 4"))
    with pytest.raises(DatasetFormatError, match="WIDTH 5 x HEIGHT 1 but POINTS 4"):
        read_pcd(path)


def test_an_all_nan_time_field_is_named(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(2):
        columns = _cloud(k)
        columns["time_stamp"] = np.full(len(columns["x"]), np.nan, dtype="<f4")
        write_pcd(folder / f"{k:06d}.pcd", columns)
    capsys.readouterr()
    args = ["replay", str(folder), "--poses", "identity", "-o", str(tmp_path / "m.npz"), *QUIET]
    assert main(args) == 1
    err = _one_error_line(capsys)
    assert "per-point time field 'time_stamp' is NaN/Inf at 400 points" in err


def test_kiss_icp_on_degenerate_clouds_is_warned(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    from mfp_mapper.sources.lidar_odometry import kiss_icp_available

    if not kiss_icp_available():
        pytest.skip("kiss-icp is not installed (requirements-dev.txt)")
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(4):
        write_pcd(folder / f"{k:06d}.pcd", _cloud(k, 3))
    capsys.readouterr()
    out = tmp_path / "m.npz"
    args = ["replay", str(folder), "--odometry", "kiss-icp", "-o", str(out), *QUIET]
    main(args)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "4 of 4 clouds have fewer than 100 points (smallest 3)" in err
