"""The project's TF buffer against scipy's rotations: chains, interpolation, stream checks."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from mfp_mapper.sensing.deskew import cloud_to_map
from mfp_mapper.sensing.pipeline import ScanDropped
from mfp_mapper.sensing.placement import resolve_placement
from mfp_mapper.sensing.pointcloud import ParsedCloud
from mfp_mapper.sensing.poses import Extrinsic
from mfp_mapper.sensing.tf_tree import (
    TfChain,
    TfTree,
    TransformUnavailable,
    compose,
    frame_list,
    invert,
)


def matrix(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(q).as_matrix()
    out[:3, 3] = t
    return out


RNG = np.random.default_rng(7)
EDGES = {  # child: (parent, translation, quaternion)
    "odom": ("map", np.array([1.0, -2.0, 0.1]), Rotation.from_euler("z", 0.3).as_quat()),
    "base_link": ("odom", np.array([4.0, 0.5, 0.0]), Rotation.from_euler("z", -1.2).as_quat()),
    "lidar": (
        "base_link",
        np.array([0.2, 0.0, 0.4]),
        Rotation.from_euler("xyz", [0.1, -0.2, 0.5]).as_quat(),
    ),
    "camera": ("base_link", np.array([0.3, 0.1, 0.2]), Rotation.random(random_state=3).as_quat()),
}


def robot_tree(stamps: tuple[float, ...] = (10.0, 11.0)) -> TfTree:
    tree = TfTree()
    for child in ("lidar", "camera"):
        parent, t, q = EDGES[child]
        tree.add(parent, child, 0.0, t, q, static=True)
    for stamp in stamps:
        for child in ("odom", "base_link"):
            parent, t, q = EDGES[child]
            tree.add(parent, child, stamp, t, q)
    return tree


def test_chain_lookup_matches_matrix_products() -> None:
    tree = robot_tree()
    expected = {child: matrix(t, q) for child, (_, t, q) in EDGES.items()}
    map_lidar = expected["odom"] @ expected["base_link"] @ expected["lidar"]
    np.testing.assert_allclose(tree.lookup_matrix("map", "lidar", 10.5), map_lidar, atol=1e-12)
    # siblings: the common ancestor is base_link
    lidar_camera = np.linalg.inv(expected["lidar"]) @ expected["camera"]
    np.testing.assert_allclose(
        tree.lookup_matrix("lidar", "camera", 10.5), lidar_camera, atol=1e-12
    )
    # downwards: the inverse
    np.testing.assert_allclose(
        tree.lookup_matrix("lidar", "map", 10.5), np.linalg.inv(map_lidar), atol=1e-12
    )
    np.testing.assert_allclose(tree.lookup_matrix("/map", "map", 10.5), np.eye(4))


def test_interpolation_is_linear_in_translation_and_slerp_in_rotation() -> None:
    tree = TfTree()
    r0, r1 = (
        Rotation.from_euler("xyz", [0.1, 0.2, 0.3]),
        Rotation.from_euler("xyz", [-0.4, 0.5, 2.0]),
    )
    tree.add("odom", "base_link", 1.0, [0.0, 0.0, 0.0], r0.as_quat())
    # the same rotation on the other hemisphere: must still take the short way
    tree.add("odom", "base_link", 3.0, [2.0, -4.0, 6.0], -r1.as_quat())
    stamps = np.array([1.0, 1.5, 2.0, 2.9, 3.0])
    t, q = tree.lookup("odom", "base_link", stamps)
    alpha = (stamps - 1.0) / 2.0
    np.testing.assert_allclose(t, alpha[:, None] * np.array([2.0, -4.0, 6.0]), atol=1e-12)
    reference = Slerp([1.0, 3.0], Rotation.concatenate([r0, r1]))(stamps)
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), reference.as_matrix(), atol=1e-12)


def test_lookup_errors_name_the_frames_and_the_edge() -> None:
    tree = robot_tree()
    with pytest.raises(TransformUnavailable) as err:
        tree.lookup("map", "lidar", [11.5])
    assert err.value.reason == "too_new" and "odom -> base_link" in str(err.value)
    with pytest.raises(TransformUnavailable) as err:
        tree.lookup("map", "lidar", [9.0])
    assert err.value.reason == "too_old"
    with pytest.raises(TransformUnavailable) as err:
        tree.lookup("map", "velodyne", [10.5])
    assert err.value.reason == "unconnected" and "'velodyne'" in str(err.value)
    gappy = TfTree(max_gap=0.5)
    gappy.add("odom", "base_link", 0.0, [0, 0, 0], [0, 0, 0, 1])
    gappy.add("odom", "base_link", 2.0, [0, 0, 0], [0, 0, 0, 1])
    with pytest.raises(TransformUnavailable) as err:
        gappy.lookup("odom", "base_link", [1.0])
    assert err.value.reason == "gap"
    np.testing.assert_allclose(gappy.lookup("odom", "base_link", [2.0])[0], [[0, 0, 0]])


def test_buffer_length_keeps_one_sample_before_the_cut() -> None:
    tree = TfTree(buffer_length=2.0)
    for k in range(11):
        tree.add("odom", "base_link", float(k), [k, 0, 0], [0, 0, 0, 1])
    np.testing.assert_allclose(tree.lookup("odom", "base_link", [8.0, 8.5])[0][:, 0], [8.0, 8.5])
    with pytest.raises(TransformUnavailable) as err:
        tree.lookup("odom", "base_link", [6.5])  # 7 is the one kept before the cut at 8
    assert err.value.reason == "too_old"
    # out of order inside the buffer is inserted in place
    tree.add("odom", "base_link", 9.5, [100, 0, 0], [0, 0, 0, 1])
    assert tree.lookup("odom", "base_link", [9.5])[0][0, 0] == 100.0
    # older than the buffer: dropped and counted (9 s back is also a jump to confirm)
    assert not tree.add("odom", "base_link", 1.0, [0, 0, 0], [0, 0, 0, 1])
    assert tree.rejected["past_outlier"] == 1
    assert not tree.add("odom", "base_link", 6.0, [0, 0, 0], [0, 0, 0, 1])
    assert tree.rejected["old"] == 1


def test_one_poisoned_future_stamp_cannot_stop_the_stream() -> None:
    tree = TfTree(max_jump=5.0)
    for k in range(5):
        assert tree.add("odom", "base_link", float(k), [k, 0, 0], [0, 0, 0, 1])
    assert not tree.add("odom", "base_link", 3600.0, [0, 0, 0], [0, 0, 0, 1])
    assert tree.rejected["future_outlier"] == 1
    for k in range(5, 8):
        assert tree.add("odom", "base_link", float(k), [k, 0, 0], [0, 0, 0, 1])
    assert tree.latest_common_stamp("odom", "base_link") == 7.0
    # a real jump forward is confirmed by the next sample
    assert not tree.add("odom", "base_link", 100.0, [0, 0, 0], [0, 0, 0, 1])
    assert tree.add("odom", "base_link", 100.1, [0, 0, 0], [0, 0, 0, 1])
    assert tree.latest_common_stamp("odom", "base_link") == pytest.approx(100.1)


def test_reference_clock_rejects_far_future_and_backward_jump_clears() -> None:
    tree = robot_tree()
    assert not tree.add("map", "odom", 1000.0, [0, 0, 0], [0, 0, 0, 1], now=12.0)
    assert tree.rejected["ahead_of_clock"] == 1
    assert tree.observe_clock(12.0) is False
    assert tree.observe_clock(13.0) is False
    assert tree.observe_clock(2.0) is True  # bag loop: dynamic edges cleared
    with pytest.raises(TransformUnavailable):
        tree.lookup("map", "lidar", [10.5])
    assert tree.static_chain("base_link", "lidar") is not None  # static edges kept
    tree.add("map", "odom", 2.0, [0, 0, 0], [0, 0, 0, 1])
    tree.add("odom", "base_link", 2.0, [0, 0, 0], [0, 0, 0, 1])
    assert tree.lookup("map", "lidar", [2.0])[0].shape == (1, 3)


def test_static_chain_and_invalid_input() -> None:
    tree = robot_tree()
    t, q = tree.static_chain("base_link", "lidar") or (None, None)
    np.testing.assert_allclose(matrix(t, q), matrix(*EDGES["lidar"][1:]), atol=1e-12)
    assert tree.static_chain("map", "lidar") is None  # crosses dynamic edges
    assert not tree.add("a", "b", 0.0, [math.nan, 0, 0], [0, 0, 0, 1])
    assert not tree.add("a", "b", 0.0, [0, 0, 0], [0, 0, 0, 0])
    assert not tree.add("a", "a", 0.0, [0, 0, 0], [0, 0, 0, 1])
    assert tree.rejected["invalid"] == 3


def test_tf_message_duck_typed_and_chain_as_pose_source() -> None:
    def transform(parent: str, child: str, stamp: float, x: float) -> SimpleNamespace:
        return SimpleNamespace(
            header=SimpleNamespace(
                frame_id=parent, stamp=SimpleNamespace(sec=int(stamp), nanosec=int(stamp % 1 * 1e9))
            ),
            child_frame_id=child,
            transform=SimpleNamespace(
                translation=SimpleNamespace(x=x, y=0.0, z=0.0),
                rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        )

    tree = TfTree()
    assert (
        tree.add_message(
            SimpleNamespace(transforms=[transform("base_link", "/lidar", 0, 0.5)]), True
        )
        == 1
    )
    for stamp, x in ((1.0, 0.0), (2.0, 1.0)):
        tree.add_message(
            SimpleNamespace(transforms=[transform("odom", "base_link", stamp, x)]), False
        )
    cloud = ParsedCloud(
        xyz=np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]),
        time_offset=np.array([0.0, 0.5]),
        intensity=None,
        points_in=2,
    )
    points, origins = cloud_to_map(cloud, 1.0, TfChain(tree, "odom", "lidar"), Extrinsic())
    np.testing.assert_allclose(points, [[1.5, 0, 0], [3.0, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(origins, [[0.5, 0, 0], [1.0, 0, 0]], atol=1e-12)


# --- tf2 semantics: expiry, one parent per frame, loops, jumps, churn ----------------------

UNIT = [0.0, 0.0, 0.0, 1.0]


def streaming(tree: TfTree, start: float, stop: float, rate: float = 50.0) -> float:
    """map -> odom -> base_link at ``rate`` Hz from ``start`` to ``stop``; the last stamp."""
    t = start
    while t <= stop + 1e-9:
        tree.add("map", "odom", t, [1.0, 0, 0], UNIT)
        tree.add("odom", "base_link", t, [t, 0, 0], UNIT)
        t += 1.0 / rate
    return t - 1.0 / rate


def test_a_loop_closing_message_is_refused_never_stored() -> None:
    tree = TfTree()
    tree.add("base_link", "velodyne", 0.0, [0, 0, 1.0], UNIT, static=True)
    streaming(tree, 10.0, 11.0)
    assert not tree.add("base_link", "odom", 11.0, [0, 0, 0], UNIT)  # odom is above base_link
    assert not tree.add("velodyne", "map", 0.0, [0, 0, 0], UNIT, static=True)
    assert tree.rejected["loop"] == 2
    kinds = [k for k, _ in tree.take_events()]
    assert kinds.count("tf_loop") == 2
    streaming(tree, 11.02, 11.5)
    assert tree.lookup_matrix("map", "velodyne", 11.4)[:3, 3].tolist() == [12.4, 0.0, 1.0]


def test_a_stray_parent_on_a_static_frame_expires_after_the_cache_time() -> None:
    """One dynamic odom -> velodyne beside the static base_link -> velodyne: the frame
    has the new parent (tf2) with one warning, and the static edge is back once the stray
    edge is older than the cache time."""
    tree = TfTree(buffer_length=2.0)
    tree.add("base_link", "velodyne", 0.0, [0, 0, 1.0], UNIT, static=True)
    streaming(tree, 10.0, 11.0)
    assert tree.add("odom", "velodyne", 11.0, [5.0, 0, 0], UNIT)
    events = tree.take_events()
    assert [k for k, _ in events] == ["tf_parent"]
    assert "'base_link'" in events[0][1] and "'odom'" in events[0][1]
    with pytest.raises(TransformUnavailable):  # one message never places a cloud
        tree.lookup("map", "velodyne", [11.0])
    end = streaming(tree, 11.02, 12.9)
    with pytest.raises(TransformUnavailable):  # only one stray sample: not at 12.9
        tree.lookup("map", "velodyne", [end])
    end = streaming(tree, end + 0.02, 13.2)  # the stray edge is > 2 s old now
    assert tree.parent("velodyne") == ("base_link", True)
    assert tree.lookup_matrix("map", "velodyne", end)[:3, 3].tolist() == pytest.approx(
        [end + 1.0, 0.0, 1.0]
    )


def test_a_single_stray_parent_on_a_dynamic_frame_costs_nothing() -> None:
    tree = TfTree()
    streaming(tree, 10.0, 11.0)
    tree.add("map", "base_link", 11.0, [99.0, 0, 0], UNIT)  # one message from a stray node
    end = streaming(tree, 11.02, 11.5)
    assert tree.parent("base_link") == ("odom", False) and not tree.conflicts()
    # the samples from before the stray are still there
    np.testing.assert_allclose(
        tree.lookup("map", "base_link", [10.5, 11.01])[0][:, 0], [11.5, 12.01]
    )
    assert end > 11.4


def test_alternating_parents_are_a_conflict_until_one_publisher_stops() -> None:
    tree = TfTree(buffer_length=2.0)
    t = 10.0
    for _ in range(20):  # two localizers: base_link in odom, then in map, ...
        tree.add("map", "odom", t, [1.0, 0, 0], UNIT)
        tree.add("odom", "base_link", t, [t, 0, 0], UNIT)
        tree.add("map", "base_link", t + 0.01, [t + 1.0, 0, 0], UNIT)
        t += 0.05
    assert tree.conflicts() == {"base_link": ("map", "odom")}
    with pytest.raises(TransformUnavailable) as err:
        tree.lookup("map", "base_link", [t - 0.1])
    assert err.value.reason == "tf_conflict"
    assert "'map'" in str(err.value) and "'odom'" in str(err.value)
    assert "tf_conflict" in [k for k, _ in tree.take_events()]
    end = streaming(tree, t, t + 2.5)  # one localizer left
    assert not tree.conflicts()
    assert tree.lookup("map", "base_link", [end])[0][0, 0] == pytest.approx(end + 1.0)


def test_a_stream_jumping_back_starts_over_after_a_second_message() -> None:
    tree = TfTree()
    streaming(tree, 100.0, 101.0)
    assert not tree.add("map", "odom", 80.0, [1.0, 0, 0], UNIT)  # one message 20 s back: held
    assert tree.rejected["past_outlier"] == 1
    end = streaming(tree, 80.0, 80.5)  # the publisher restarted with its clock 20 s back
    assert tree.lookup("map", "base_link", [end - 0.1])[0][0, 0] == pytest.approx(end + 0.9)
    assert "tf_jump" in [k for k, _ in tree.take_events()]
    # one far-future message does not move the stream
    assert not tree.add("map", "odom", 5000.0, [1.0, 0, 0], UNIT)
    end = streaming(tree, end + 0.02, end + 0.5)
    assert tree.lookup("map", "base_link", [end])[0][0, 0] == pytest.approx(end + 1.0)


def test_churned_frame_names_are_forgotten_and_errors_stay_short() -> None:
    """60k frame names, each published for a moment: the tree holds only the last cache
    time's worth, and an error line names at most a handful of frames."""
    tree = TfTree(buffer_length=1.0)
    for k in range(60_000):
        t = 1000.0 + 0.001 * k  # 60 s of stream, 1000 new names per second
        tree.add("map", f"frame_{k}", t, [0, 0, 0], UNIT)
    assert len(tree.frames()) <= 1 + 2 * 1000 + 64
    with pytest.raises(TransformUnavailable) as err:
        tree.lookup("map", "nowhere", [1059.0])
    assert len(str(err.value)) < 300 and "more" in str(err.value)
    for k in range(3000):  # 3000 live frames: the placement's drop line stays short too
        tree.add("map", f"live_{k}", 1060.0, [0, 0, 0], UNIT)
    with pytest.raises(ScanDropped) as drop:
        resolve_placement("nowhere", tree, None)
    assert len(drop.value.detail) < 300 and " more)" in drop.value.detail, drop.value.detail
    assert frame_list(["c", "a", "b"], limit=2) == "'a', 'b' and 1 more"


def test_rotations_compose_like_matrix_products() -> None:
    rng = np.random.default_rng(1)
    q1, q2 = (
        Rotation.random(50, random_state=2).as_quat(),
        Rotation.random(50, random_state=3).as_quat(),
    )
    t1, t2 = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    t, q = compose((t1, q1), (t2, q2))
    for k in range(50):
        expected = matrix(t1[k], q1[k]) @ matrix(t2[k], q2[k])
        np.testing.assert_allclose(matrix(t[k], q[k]), expected, atol=1e-12)
    ti, qi = invert((t1, q1))
    for k in range(5):
        np.testing.assert_allclose(
            matrix(ti[k], qi[k]), np.linalg.inv(matrix(t1[k], q1[k])), atol=1e-12
        )


def test_a_snapshot_of_some_frames_holds_their_chains_only() -> None:
    """Placement copies only the chains it looks up: the whole tree took 300 ms under the
    lock at 20,000 frames (a TF flood), holding up the executor."""
    tree = TfTree(buffer_length=10.0)
    for k in range(20):
        tree.add("odom", "base_link", 100.0 + 0.1 * k, (0.1 * k, 0.0, 0.0), (0, 0, 0, 1))
    for stamp in (100.0, 101.0):
        tree.add("map", "odom", stamp, (1.0, 2.0, 0.0), (0, 0, 0, 1))
    tree.add("base_link", "lidar", 0.0, (0.0, 0.0, 1.0), (0, 0, 0, 1), static=True)
    for k in range(2_000):
        tree.add("map", f"flood_{k}", 101.0, (0.0, 0.0, 0.0), (0, 0, 0, 1))
    part = tree.snapshot(("lidar", "map"))
    assert part.frames() == {"lidar", "base_link", "odom", "map"}
    np.testing.assert_allclose(
        part.lookup_matrix("map", "lidar", 100.55), tree.lookup_matrix("map", "lidar", 100.55)
    )
    assert len(tree.snapshot().frames()) == 2_004
