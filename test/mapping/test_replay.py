"""Replaying recordings: bags (formats, topic detection, poses from Odometry or /tf,
extrinsics), folders of scan files, the simulator; the same map from the same rays."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from folder_helpers import bag_contents, write_pcd, write_ply

from mfp_mapper.config.schema import xyz_rpy
from mfp_mapper.mapping.replay import (
    Progress,
    ReplayError,
    ReplayOptions,
    options_from_yaml,
    replay,
)
from mfp_mapper.sensing.poses import PoseBuffer, quaternion_to_matrix, rpy_to_quaternion
from mfp_mapper.sources.opener import open_recording
from mfp_mapper.sources.simulate import VELODYNE_DTYPE, VELODYNE_FIELDS, BagSink, preset, simulate

SMALL = replace(preset("small"), scans=6, azimuths=240)
RES = 0.25


def _bag(root: Path, name: str, fmt: str | None = None, **changes: object) -> Path:
    return simulate(root / name, replace(SMALL, **changes), fmt).bag


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {
        "mcap": _bag(root, "mcap", "mcap"),
        "sqlite3": _bag(root, "sqlite3", "sqlite3"),
        "ros1": _bag(root, "run.bag", "ros1"),
        "tf_only": _bag(root, "tf_only", odom_topic=None, write_tf=True),
        "base_frame": _bag(root, "base_frame", cloud_in_base_frame=True, write_tf_static=False),
        "no_static": _bag(root, "no_static", write_tf_static=False),
    }


def _stats(bag: Path, **opts: object) -> tuple[np.ndarray, np.ndarray, object]:
    result = replay(bag, ReplayOptions.of(resolution=RES, **opts), progress=False)  # type: ignore[arg-type]
    v = result.mapper.voxels()
    order = np.lexsort(v.ijk.T)
    return v.ijk[order], np.stack([v.s[order], v.n[order]]), result.summary


@pytest.fixture(scope="module")
def reference(bags: dict[str, Path]) -> tuple[np.ndarray, np.ndarray, object]:
    return _stats(bags["mcap"])


@pytest.mark.parametrize("fmt", ["sqlite3", "ros1"])
def test_all_storage_formats_give_the_same_map(bags, reference, fmt: str) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, summary = _stats(bags[fmt])
    np.testing.assert_array_equal(ijk, reference[0])
    np.testing.assert_allclose(sn, reference[1], rtol=1e-9, atol=1e-9)
    assert summary.scans_used == SMALL.scans


def test_summary_of_a_replay(bags, reference) -> None:  # type: ignore[no-untyped-def]
    summary = reference[2]
    assert summary.cloud_topic == "/velodyne_points"
    assert summary.map_frame == "odom" and summary.cloud_frame == "velodyne"
    assert "/odom" in summary.pose_source
    assert summary.extrinsic_source.startswith("/tf_static")
    assert summary.deskew
    assert summary.scans_total == summary.scans_used == SMALL.scans
    assert summary.points_in == summary.rays_used == SMALL.scans * SMALL.azimuths * 16
    assert summary.voxels > 0 and 0.0 <= summary.share_outside_core <= 1.0
    text = summary.format()
    assert "rays/s" in text and "outside the core" in text


def test_explicit_topics_match_auto_detection(bags, reference) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, _ = _stats(bags["mcap"], cloud_topic="/velodyne_points", odom_topic="/odom")
    np.testing.assert_array_equal(ijk, reference[0])
    np.testing.assert_allclose(sn, reference[1])


def test_poses_from_the_tf_chain(bags, reference) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, summary = _stats(bags["tf_only"])
    assert summary.pose_source.startswith("/tf chain odom -> base_link")
    np.testing.assert_array_equal(ijk, reference[0])
    np.testing.assert_allclose(sn, reference[1], rtol=1e-6, atol=1e-6)


def test_extrinsic_from_tf_static_matters(bags, reference) -> None:  # type: ignore[no-untyped-def]
    # the bag's /tf_static holds the true mount; a wrong one given explicitly moves the map
    wrong = xyz_rpy([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    ijk, _, summary = _stats(bags["mcap"], extrinsic=wrong)
    assert summary.extrinsic_source == "given on the command line"
    assert ijk.shape != reference[0].shape or not np.array_equal(ijk, reference[0])
    # the true one given explicitly reproduces the /tf_static map
    t, rpy = SMALL.lidar_translation, SMALL.lidar_rpy
    ijk2, sn2, _ = _stats(bags["no_static"], extrinsic=xyz_rpy(t, rpy))
    np.testing.assert_array_equal(ijk2, reference[0])
    np.testing.assert_allclose(sn2, reference[1], rtol=1e-6, atol=1e-6)


def test_identity_when_the_cloud_is_in_the_odometry_child_frame(bags, reference) -> None:  # type: ignore[no-untyped-def]
    ijk, sn, summary = _stats(bags["base_frame"])
    assert summary.extrinsic_source.startswith("identity")
    # same returns (rays now start at the base_link origin, so the crossed voxels differ)
    hit_ref = {tuple(v): n for v, n in zip(reference[0], reference[1][1], strict=True) if n > 0}
    hit = {tuple(v): n for v, n in zip(ijk, sn[1], strict=True) if n > 0}
    assert sum(hit.values()) == sum(hit_ref.values())
    same = sum(1 for k in hit if k in hit_ref and hit[k] == hit_ref[k])
    assert same >= 0.97 * len(hit_ref)  # float32 points on the floor z = 0 may change voxel


def test_missing_extrinsic_is_an_error_unless_configured(bags, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ReplayError, match="no lidar extrinsic"):
        replay(bags["no_static"], ReplayOptions.of(resolution=RES), progress=False)
    cfg = tmp_path / "node.yaml"
    t, rpy = SMALL.lidar_translation, SMALL.lidar_rpy
    cfg.write_text(
        "mfp_mapper:\n  ros__parameters:\n    resolution: 0.25\n"
        "    sensor_model:\n      max_range: 0.0\n"
        f"    lidar.translation: {list(t)}\n    lidar.rpy: {list(rpy)}\n"
    )
    opts = options_from_yaml(cfg)
    assert opts["resolution"] == 0.25 and opts["max_range"] == 0.0  # no limit to the core
    result = replay(bags["no_static"], ReplayOptions.of(**opts), progress=False)
    assert "configuration" in result.summary.extrinsic_source


def test_unknown_config_parameter_is_an_error(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("/**:\n  ros__parameters:\n    resolution: 0.2\n    resolutoin: 0.1\n")
    with pytest.raises(ReplayError, match="resolutoin"):
        options_from_yaml(cfg)
    # rcl cannot read a file without a node section: neither can --config (a former leniency)
    cfg.write_text("resolution: 0.2\n")
    with pytest.raises(ReplayError, match="ros__parameters"):
        options_from_yaml(cfg)


def _bag_with_late_clouds(path: Path) -> Path:
    """Odometry for t in [0, 1] s, clouds at t = 100 s: no pose covers them."""
    records = np.zeros(10, dtype=VELODYNE_DTYPE)
    records["x"] = 2.0
    with BagSink(path, "sqlite3") as sink:
        sink.add("/odom", "nav_msgs/msg/Odometry")
        sink.add("/cloud", "sensor_msgs/msg/PointCloud2")
        q = rpy_to_quaternion(0, 0, 0)
        for t in np.arange(0.0, 1.0, 0.1):
            sink.write("/odom", t, sink.odometry(t, "odom", "base_link", np.zeros(3), q, 0, 0))
        for t in (100.0, 100.1):
            sink.write("/cloud", t, sink.pointcloud(t, "base_link", records, VELODYNE_FIELDS))
    return path


def test_no_pose_covering_the_clouds(tmp_path: Path) -> None:
    bag = _bag_with_late_clouds(tmp_path / "late")
    with pytest.raises(ReplayError, match="No pose covers the clouds") as info:
        replay(bag, progress=False)
    assert "too_new 2" in str(info.value)


def test_ros2_file_path_means_its_folder(bags) -> None:  # type: ignore[no-untyped-def]
    mcap_file = next(bags["mcap"].glob("*.mcap"))
    result = replay(mcap_file, ReplayOptions.of(resolution=RES, max_scans=2), progress=False)
    assert result.summary.scans_used == 2


def test_progress_line_reports_rate_and_time_left() -> None:
    import io

    stream = io.StringIO()
    bar = Progress(10, stream=stream, interval=0.0)
    bar.update(5, 50_000, force=True)
    text = stream.getvalue()
    assert "5/10 scans" in text and "rays/s" in text and "left" in text


def test_keep_radius_reaches_the_mapper(bags) -> None:  # type: ignore[no-untyped-def]
    full = replay(bags["mcap"], ReplayOptions.of(resolution=RES), progress=False).mapper
    near = replay(bags["mcap"], ReplayOptions.of(resolution=RES, keep_radius=1.0), progress=False)
    assert near.mapper.keep_radius == 1.0 and full.keep_radius is None
    assert 0 < near.mapper.num_voxels < full.num_voxels


def _sorted(result) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[no-untyped-def]
    v = result.mapper.voxels()
    order = np.lexsort(v.ijk.T)
    return v.ijk[order], np.stack([v.s[order], v.n[order]])


def _same(a, b) -> None:  # type: ignore[no-untyped-def]
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1], rtol=1e-9, atol=1e-9)


def test_one_opened_recording_replays_twice_to_the_same_map(bags) -> None:  # type: ignore[no-untyped-def]
    opts = ReplayOptions.of(resolution=RES)
    with open_recording(bags["mcap"], opts) as recording:
        first = replay(recording, opts, progress=False)
        second = replay(recording, opts, progress=False)
    _same(_sorted(first), _sorted(second))
    assert first.summary.pose_source == second.summary.pose_source


def test_the_simulator_without_a_bag_maps_as_its_bag(bags) -> None:  # type: ignore[no-untyped-def]
    """The same clouds placed by the true path instead of the recorded 50 Hz odometry: the
    same returns, placed within the odometry's interpolation error (a chord of the circle,
    0.08 mm); points on the floor (z = 0) may change voxel."""
    opts = ReplayOptions.of(resolution=RES)
    placed: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"bag": [], "sim": []}

    def keep(name: str):  # type: ignore[no-untyped-def]
        return lambda _, points, origins: placed[name].append((points.copy(), np.copy(origins)))

    from_bag = replay(bags["mcap"], opts, progress=False, on_scan=keep("bag"))
    simulated = replay(open_recording(SMALL, opts), opts, progress=False, on_scan=keep("sim"))
    assert "true path" in simulated.summary.pose_source
    assert simulated.summary.rays_used == from_bag.summary.rays_used
    assert simulated.mapper.frame_id == from_bag.mapper.frame_id == "odom"
    assert len(placed["sim"]) == len(placed["bag"]) == SMALL.scans
    for (p_sim, o_sim), (p_bag, o_bag) in zip(placed["sim"], placed["bag"], strict=True):
        assert np.abs(p_sim - p_bag).max() < 2e-4 and np.abs(o_sim - o_bag).max() < 2e-4
    _, sn = _sorted(simulated)
    _, ref_sn = _sorted(from_bag)
    assert sn[1].sum() == ref_sn[1].sum()  # every return counted once
    assert abs(sn[0].sum() - ref_sn[0].sum()) < 1e-3 * ref_sn[0].sum()


# --- folders of scan files: the same map as the bag of the same rays -------------------------

IN_BASE = replace(SMALL, cloud_in_base_frame=True)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A simulated bag (clouds in base_link: the odometry is the lidar's pose) and its
    clouds and poses."""
    root = tmp_path_factory.mktemp("folder")
    bag = simulate(root / "bag", IN_BASE, "mcap").bag
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
    with open_recording(folder, opts, poses=tum) as scans:
        from_folder = replay(scans, opts, progress=False)
    assert from_folder.summary.deskew and from_bag.summary.deskew
    assert from_folder.summary.scans_used == IN_BASE.scans
    assert from_folder.summary.rays_used == from_bag.summary.rays_used
    assert from_folder.summary.cloud_topic.endswith(".pcd files (stamps: file names)")
    _same(_sorted(from_folder), _sorted(from_bag))


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
    with open_recording(folder, opts, poses=poses) as scans:
        from_folder = replay(scans, opts, progress=False)
    assert from_folder.summary.scans_used == IN_BASE.scans
    ijk, sn = _sorted(from_folder)
    ref_ijk, ref_sn = _sorted(from_bag)
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
    _same(_sorted(by_time), _sorted(by_index))
    _same(_sorted(by_offset), _sorted(by_index))
    with pytest.raises(ReplayError, match="no cloud could be mapped"):
        replay(recording["bag"], full.but(start=stamps[-1] + 1), progress=False)


def test_identity_poses_for_single_frames(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    xyz = np.array([[5.0, 0.0, 0.0], [0.0, 4.0, 0.0]], dtype="<f4")
    write_ply(folder / "a.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    opts = ReplayOptions.of(resolution=0.5)
    result = replay(open_recording(folder, opts, poses="identity"), opts, progress=False)
    hit = result.mapper.query([[5.2, 0.2, 0.2], [0.2, 4.2, 0.2]])
    assert np.all(hit.n == 1)
    assert result.mapper.frame_id == "lidar"


def test_a_folder_needs_poses_when_replayed_by_its_path(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    write_ply(folder / "a.ply", {"x": np.ones(2, "<f4"), "y": np.ones(2, "<f4"),
                                 "z": np.ones(2, "<f4")})  # fmt: skip
    with pytest.raises(ReplayError, match="a scan folder needs poses"):
        replay(folder, progress=False)
