"""Folders of scan files replay to the same map as the bag of the same rays."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from folder_helpers import bag_contents, write_pcd, write_ply

from mfp_mapper.mapping.folder_replay import replay_folder
from mfp_mapper.mapping.replay import ReplayOptions, replay
from mfp_mapper.sensing.poses import PoseBuffer, quaternion_to_matrix
from mfp_mapper.sources.bags import ReplayError
from mfp_mapper.sources.pose_files import matrix_to_quaternion
from mfp_mapper.sources.simulate import preset, simulate

SMALL = replace(preset("small"), scans=6, azimuths=240, cloud_in_base_frame=True)
RES = 0.25


def _stats(result) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    v = result.mapper.voxels()
    order = np.lexsort(v.ijk.T)
    return v.ijk[order], np.stack([v.s[order], v.n[order]])


def _same(a, b) -> None:  # type: ignore[no-untyped-def]
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1], rtol=1e-9, atol=1e-9)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A simulated bag (clouds in base_link: the odometry is the lidar's pose) and its
    clouds and poses."""
    root = tmp_path_factory.mktemp("folder")
    bag = simulate(root / "bag", SMALL, "mcap").bag
    clouds, odometry = bag_contents(bag)
    return {"root": root, "bag": bag, "clouds": clouds, "odometry": odometry}


def _columns(records: np.ndarray, time: bool) -> dict[str, np.ndarray]:
    names = ["x", "y", "z", "intensity"] + (["time"] if time else [])
    return {n: records[n].copy() for n in names}


def test_pcd_folder_with_tum_poses_equals_the_bag_deskewed(recording) -> None:  # type: ignore[no-untyped-def]
    folder = recording["root"] / "pcd"
    folder.mkdir()
    for k, (stamp, records) in enumerate(recording["clouds"]):
        sec = int(stamp)
        nsec = round((stamp - sec) * 1e9)
        write_pcd(folder / f"cloud_{sec}_{nsec}.pcd", _columns(records, True), binary=k % 2 == 0)
    tum = recording["root"] / "odom.tum"
    np.savetxt(tum, recording["odometry"], fmt="%.17g", header="t x y z qx qy qz qw")
    opts = ReplayOptions.of(resolution=RES)
    from_bag = replay(recording["bag"], opts, progress=False)
    from_folder = replay_folder(folder, tum, opts, progress=False)
    assert from_folder.summary.deskew and from_bag.summary.deskew
    assert from_folder.summary.scans_used == SMALL.scans
    assert from_folder.summary.rays_used == from_bag.summary.rays_used
    _same(_stats(from_folder), _stats(from_bag))


def test_kitti_folder_with_kitti_poses_equals_the_bag_without_deskew(recording) -> None:  # type: ignore[no-untyped-def]
    folder = recording["root"] / "kitti" / "velodyne"
    folder.mkdir(parents=True)
    odometry = recording["odometry"]
    buffer = PoseBuffer(max_age=np.inf, max_gap=1.0)
    for row in odometry:
        buffer.add(row[0], row[1:4], row[4:8])
    stamps = [stamp for stamp, _ in recording["clouds"]]
    positions, quaternions = buffer.interpolate_quaternions(stamps)
    lines = []
    for k, (_, records) in enumerate(recording["clouds"]):
        xyzi = np.stack([records[n] for n in ("x", "y", "z", "intensity")], axis=1)
        xyzi.astype("<f4").tofile(folder / f"{k:06d}.bin")
        matrix = np.hstack([quaternion_to_matrix(quaternions[k]), positions[k][:, None]])
        lines.append(" ".join(f"{v:.17g}" for v in matrix.reshape(-1)))
    (folder.parent / "times.txt").write_text("\n".join(f"{s:.9f}" for s in stamps) + "\n")
    poses = folder.parent / "poses.txt"
    poses.write_text("\n".join(lines) + "\n")
    opts = ReplayOptions.of(resolution=RES, deskew=False)
    from_bag = replay(recording["bag"], opts, progress=False)
    from_folder = replay_folder(folder, poses, opts, progress=False)
    assert from_folder.summary.scans_used == SMALL.scans
    ijk, sn = _stats(from_folder)
    ref_ijk, ref_sn = _stats(from_bag)
    # the same rays up to the rounding of a pose through a 3x4 matrix (1e-16)
    assert abs(len(ijk) - len(ref_ijk)) <= 2
    assert abs(sn[0].sum() - ref_sn[0].sum()) < 1e-6 * ref_sn[0].sum()
    np.testing.assert_array_equal(sn[1].sum(), ref_sn[1].sum())


def test_selection_window_and_every(recording) -> None:  # type: ignore[no-untyped-def]
    stamps = [stamp for stamp, _ in recording["clouds"]]
    full = ReplayOptions.of(resolution=RES)
    by_index = replay(
        recording["bag"], full.but(start_index=1, end_index=5, every=2), progress=False
    )
    by_time = replay(
        recording["bag"], full.but(start=stamps[1], end=stamps[5], every=2), progress=False
    )
    by_offset = replay(
        recording["bag"],
        full.but(
            start_offset=stamps[1] - stamps[0],
            end_offset=stamps[4] - stamps[0] + 0.01,
            every=2,
        ),
        progress=False,
    )
    assert by_index.summary.scans_used == 2  # clouds 1 and 3
    assert (by_index.summary.first_stamp, by_index.summary.last_stamp) == (stamps[1], stamps[3])
    _same(_stats(by_time), _stats(by_index))
    _same(_stats(by_offset), _stats(by_index))
    with pytest.raises(ReplayError, match="no cloud could be mapped"):
        replay(recording["bag"], full.but(start=stamps[-1] + 1), progress=False)


def test_identity_poses_for_single_frames(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    xyz = np.array([[5.0, 0.0, 0.0], [0.0, 4.0, 0.0]], dtype="<f4")
    write_ply(folder / "a.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    result = replay_folder(folder, "identity", ReplayOptions.of(resolution=0.5), progress=False)
    hit = result.mapper.query([[5.2, 0.2, 0.2], [0.2, 4.2, 0.2]])
    assert np.all(hit.n == 1)
    assert result.mapper.frame_id == "lidar"


def test_folder_errors(tmp_path: Path, recording) -> None:  # type: ignore[no-untyped-def]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ReplayError, match="no scan files"):
        replay_folder(empty, "identity", progress=False)
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(3):
        write_pcd(
            folder / f"{k}.pcd",
            {"x": np.ones(3, "<f4"), "y": np.zeros(3, "<f4"), "z": np.zeros(3, "<f4")},
        )
    with pytest.raises(ReplayError, match="needs poses"):
        replay_folder(folder, None, progress=False)
    kitti = tmp_path / "poses.txt"
    kitti.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ReplayError, match="1 KITTI poses for 3 scans"):
        replay_folder(folder, kitti, progress=False)
    tum = tmp_path / "poses.tum"
    tum.write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")
    with pytest.raises(ReplayError, match="no stamps"):
        replay_folder(folder, tum, progress=False)


def test_matrix_to_quaternion_round_trip() -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[:4] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    back = matrix_to_quaternion(quaternion_to_matrix(q))
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)


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
        replay_folder(folder, None, ReplayOptions.of(odometry="kiss-icp"), progress=False)
