"""``mfp-mapper localize`` as docs/localization.md tells the user to type it, on the real
ouster_street scans: map scans 0 and 2 with ``replay``, then localize scan 1 from a pose 0.3 m
and 3 deg off its recorded pose; the refined pose comes back within 5 cm and 0.5 deg."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mfp_mapper.cli import main
from mfp_mapper.sources.pose_files import read_kitti_poses, read_tum_poses


def _tum_line(t: float, p: np.ndarray, q: np.ndarray) -> str:
    return f"{t} {p[0]} {p[1]} {p[2]} {q[0]} {q[1]} {q[2]} {q[3]}\n"


def test_localize_brings_a_perturbed_real_scan_back(shared_data: Path, tmp_path: Path) -> None:
    src = shared_data / "ouster_street"
    pos, quat = read_kitti_poses(src / "poses.txt")
    scans = sorted((src / "scans").glob("*.bin"))
    train = tmp_path / "train"
    train.mkdir()
    for k in (0, 2):
        (train / scans[k].name).symlink_to(scans[k])
    lines = (src / "poses.txt").read_text().splitlines()
    (tmp_path / "train.kitti").write_text(lines[0] + "\n" + lines[2] + "\n")
    out_map = tmp_path / "map.npz"
    assert main(["replay", str(train), "--poses", str(tmp_path / "train.kitti"), "-o",
                 str(out_map), "--resolution", "0.2", "-q"]) == 0  # fmt: skip

    test = tmp_path / "test"
    test.mkdir()
    (test / scans[1].name).symlink_to(scans[1])
    (tmp_path / "times.txt").write_text("10.0\n")
    rng = np.random.default_rng(5)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    turn = Rotation.from_rotvec(axis * math.radians(3.0))
    p0 = pos[1] + 0.3 * direction
    q0 = (turn * Rotation.from_quat(quat[1])).as_quat()
    guess = tmp_path / "guess.tum"
    guess.write_text(_tum_line(9.9, p0, q0) + _tum_line(10.1, p0, q0))
    refined = tmp_path / "refined.tum"
    assert main(["localize", str(out_map), str(test), "--poses", str(guess), "--times",
                 str(tmp_path / "times.txt"), "--poses-out", str(refined)]) == 0  # fmt: skip

    stamps, positions, quats = read_tum_poses(refined)
    assert stamps.tolist() == [10.0]
    shift = float(np.linalg.norm(positions[0] - pos[1]))
    angle = math.degrees(
        (Rotation.from_quat(quats[0]).inv() * Rotation.from_quat(quat[1])).magnitude()
    )
    assert shift < 0.05 and angle < 0.5, (shift, angle)
    rows = [
        json.loads(x)
        for x in refined.with_name("refined.tum.confidence.jsonl").read_text().splitlines()
    ]
    assert rows[0]["accepted"] is True and rows[0]["shift_m"] > 0.2
    assert all(v is not None and v < 0.05 for v in rows[0]["sigma"][:3])


def test_localize_says_why_when_the_map_is_broken(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    empty_map = tmp_path / "m.npz"
    empty_map.write_bytes(b"")
    code = main(["localize", str(empty_map), str(tmp_path / "nothing.bag"), "--poses-out",
                 str(tmp_path / "o.tum")])  # fmt: skip
    assert code == 1
    err = capsys.readouterr().err
    assert "unreadable or truncated map file" in err and "Traceback" not in err


def test_replay_refine_poses_keeps_good_poses_and_writes_them(
    shared_data: Path, tmp_path: Path
) -> None:
    """ouster_street with its own (good) poses: refinement moves no scan by more than 5 cm,
    the first scan has nothing to align against, and --poses-out has one line per scan."""
    src = shared_data / "ouster_street"
    pos, _ = read_kitti_poses(src / "poses.txt")
    out = tmp_path / "used.tum"
    code = main(["replay", str(src / "scans"), "--poses", str(src / "poses.txt"), "-o",
                 str(tmp_path / "m.npz"), "--resolution", "0.2", "--refine-poses",
                 "--poses-out", str(out)])  # fmt: skip
    assert code == 0
    _, positions, _ = read_tum_poses(out)
    assert positions.shape == (3, 3)
    assert np.max(np.linalg.norm(positions - pos, axis=1)) < 0.05
    rows = [
        json.loads(x)
        for x in out.with_name("used.tum.confidence.jsonl").read_text().split("\n")
        if x
    ]
    assert rows[0]["reason"].startswith("first scan")
    assert all(r["rays"] > 0 for r in rows[1:])
    assert (tmp_path / "m.npz").stat().st_size > 0


def _empty_map(path: Path) -> Path:
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.mapio.loading import save_map

    save_map(Mapper(0.2, frame_id="map"), path)
    return path


def test_localize_refuses_an_unwritable_confidence_file_before_any_work(
    tmp_path: Path,
    capsys,  # type: ignore[no-untyped-def]
) -> None:
    """The confidence file (FILE.confidence.jsonl) is checked with the poses: no traceback
    after the poses were written, nothing half written."""
    out = tmp_path / "o.tum"
    (tmp_path / "o.tum.confidence.jsonl").mkdir()
    for argv in (
        ["localize", str(_empty_map(tmp_path / "m.npz")), str(tmp_path / "in"),
         "--poses-out", str(out)],
        ["replay", str(tmp_path / "in"), "-o", str(tmp_path / "r.npz"), "--poses-out",
         str(out)],
    ):  # fmt: skip
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert "o.tum.confidence.jsonl is a directory" in err, err
        assert "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert not out.exists()


def test_localize_refuses_an_empty_map(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    code = main(["localize", str(_empty_map(tmp_path / "m.npz")), str(tmp_path / "in"),
                 "--poses-out", str(tmp_path / "o.tum")])  # fmt: skip
    assert code == 1
    err = capsys.readouterr().err
    assert "the map is empty" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o.tum").exists()


def test_replay_refine_poses_refuses_a_fleet_in_one_line(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    for extra in (["b"], ["--workers", "2"]):
        argv = ["replay", str(tmp_path / "a"), *extra, "--refine-poses", "-o",
                str(tmp_path / "m.npz")]  # fmt: skip
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert "take one input, a scan folder or a bag" in err, err
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "m.npz").exists()


def test_poses_out_never_replaces_what_the_command_reads(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """``--poses-out`` naming the map, the --poses file (or via a symlink) is refused before
    any work: the file is kept byte for byte."""
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.mapio.loading import save_map

    mapper = Mapper(0.2, frame_id="map")
    mapper.integrate(np.array([[2.0, 0.0, 0.0]]), np.zeros(3), 1.0)
    save_map(mapper, tmp_path / "m.npz")
    guess = tmp_path / "guess.tum"
    guess.write_text("9.9 0 0 0 0 0 0 1\n10.1 0 0 0 0 0 0 1\n")
    (tmp_path / "link.tum").symlink_to(guess)
    before = {p: p.read_bytes() for p in (tmp_path / "m.npz", guess)}
    cases = [
        (["localize", str(tmp_path / "m.npz"), str(tmp_path / "in"), "--poses", str(guess),
          "--poses-out", str(tmp_path / "m.npz")], "is the map"),
        (["localize", str(tmp_path / "m.npz"), str(tmp_path / "in"), "--poses", str(guess),
          "--poses-out", str(tmp_path / "link.tum")], "is the --poses file"),
        (["replay", str(tmp_path / "in"), "-o", str(tmp_path / "m.npz"), "--poses",
          str(guess), "--poses-out", str(guess)], "is the --poses file"),
        (["replay", str(tmp_path / "in"), "-o", str(tmp_path / "m.npz"), "--poses-out",
          str(tmp_path / "m.npz")], "is the map (-o)"),
    ]  # fmt: skip
    for argv, words in cases:
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1, (argv, err)
        assert {p: p.read_bytes() for p in before} == before


def test_a_pose_far_beyond_the_map_says_where_the_scan_went(
    shared_data: Path,
    tmp_path: Path,
    capsys,  # type: ignore[no-untyped-def]
) -> None:
    """An initial pose 10,000 km away (a pose file in another unit or frame): the scan is
    not moved, keeps its pose, and the summary says why. (Geo-referenced coordinates are
    placed since the band means no limit by default: the scan is kept and found not to
    constrain a pose, instead of being dropped as outside a +-1000 km band.)"""
    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.mapio.loading import save_map

    mapper = Mapper(0.2, frame_id="map")
    mapper.integrate(np.array([[2.0, 0.0, 0.0]]), np.zeros(3), 1.0)
    save_map(mapper, tmp_path / "m.npz")
    scans = tmp_path / "scans"
    scans.mkdir()
    (scans / "000001.bin").symlink_to(shared_data / "ouster_street" / "scans" / "000001.bin")
    (tmp_path / "times.txt").write_text("10.0\n")
    guess = tmp_path / "guess.tum"
    guess.write_text("9.9 1e7 0 0 0 0 0 1\n10.1 1e7 0 0 0 0 0 1\n")
    out = tmp_path / "o.tum"
    assert main(["localize", str(tmp_path / "m.npz"), str(scans), "--poses", str(guess),
                 "--times", str(tmp_path / "times.txt"), "--poses-out", str(out)]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "0 corrections accepted" in printed and "kept the initial pose" in printed
    assert "degenerate geometry" in printed  # why: nothing of the map around it
    row = json.loads(out.with_name("o.tum.confidence.jsonl").read_text())
    assert "degenerate" in str(row), row
    assert read_tum_poses(out)[1][0][0] == 1e7  # kept as given


def test_align_flags_out_of_range_are_refused_in_one_line(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """A level count that overflows a float (traceback before) or costs seconds for nothing,
    and a max sigma of inf or nan (which would accept corrections along a corridor's axis)."""
    base = ["localize", str(tmp_path / "m.npz"), str(tmp_path / "in"), "--poses-out",
            str(tmp_path / "o.tum")]  # fmt: skip
    for flags in (
        ["--align-levels", "100000000"],
        ["--align-levels", "13"],
        ["--align-levels", "0"],
        ["--align-max-sigma", "inf"],
        ["--align-max-sigma", "nan"],
        ["--align-rays", "5"],
    ):
        assert main([*base, *flags]) == 1, flags
        err = capsys.readouterr().err
        assert "--align-levels 1 to 12" in err and len(err.strip().splitlines()) == 1, err
