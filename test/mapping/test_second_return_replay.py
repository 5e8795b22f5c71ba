"""Replaying a bag recorded from ouster-ros in dual-return mode (``points`` + ``points2``)
with ``second_return_topic``: the clouds are paired as the node pairs them (same pixel,
same stamp), both returns of a pixel integrated as one shot, and the summary counts the
pairs as ``~/status`` does. Real bags written with rosbags."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mfp_mapper.config.sections import SensorModelSection
from mfp_mapper.mapping.loop import ScanLoop
from mfp_mapper.mapping.replay import ReplayError, ReplayOptions, new_mapper, replay
from mfp_mapper.sensing.pipeline import ReturnPair
from mfp_mapper.sensing.poses import Extrinsic, rpy_to_quaternion
from mfp_mapper.sensing.return_pairs import ReturnPairer
from mfp_mapper.sources.opener import open_recording
from mfp_mapper.sources.simulate import BagSink

HEIGHT, WIDTH = 4, 32
FIRST, SECOND = "/ouster/points", "/ouster/points2"
BLIND = SensorModelSection().echo_blind_stretch
OPTS = ReplayOptions.of(resolution=0.25, max_range=50.0)
PAIRED = OPTS.but(second_return_topic=SECOND)
OUSTER_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_pad", "<f4"), ("intensity", "<f4"),
     ("t", "<u4"), ("reflectivity", "<u2"), ("ring", "<u2"), ("ambient", "<u2"),
     ("range", "<u4")]
)  # fmt: skip


def _ranges(k: int) -> tuple[np.ndarray, np.ndarray]:
    """First and second ranges of scan ``k`` (0: no return): a second return in every third
    column, 1.5 m (or, in column 1, 0.3 m: inside the blind stretch) behind the first."""
    first = 5.0 + 0.01 * np.arange(HEIGHT * WIDTH).reshape(HEIGHT, WIDTH) + 0.2 * k
    first[0, :4] = 0.0
    second = np.where((np.arange(WIDTH) % 3 == 0)[None, :], first + 1.5, 0.0)
    second[:, 1] = first[:, 1] + 0.3
    second[first == 0.0] = 0.0
    return first, second


def _records(r: np.ndarray, width: int = WIDTH) -> np.ndarray:
    el = np.radians(np.linspace(-10.0, 10.0, HEIGHT))[:, None] * np.ones((1, width))
    az = np.radians(np.linspace(0.0, 180.0, width))[None, :] * np.ones((HEIGHT, 1))
    unit = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    p = unit * r[..., None]
    records = np.zeros((HEIGHT, width), dtype=OUSTER_DTYPE)
    for k, axis in enumerate("xyz"):
        records[axis] = p[..., k]
    records["reflectivity"] = 100
    records["ring"] = np.arange(HEIGHT)[:, None]
    records["range"] = np.round(r * 1000).astype(np.uint32)
    return records


def _write_bag(path: Path, clouds: list[tuple[str, float, float, np.ndarray]]) -> Path:
    """A bag of odometry (standing still, odom -> os_lidar) and ``clouds``: (topic, header
    stamp, receive time, records)."""
    with BagSink(path, "mcap") as sink:
        sink.add("/odom", "nav_msgs/msg/Odometry")
        sink.add(FIRST, "sensor_msgs/msg/PointCloud2")
        sink.add(SECOND, "sensor_msgs/msg/PointCloud2")
        q = rpy_to_quaternion(0.0, 0.0, 0.0)
        messages: list[tuple[float, str, Any]] = [
            (t, "/odom", sink.odometry(t, "odom", "os_lidar", np.zeros(3), q, 0.0, 0.0))
            for t in np.arange(0.0, 3.0, 0.05)
        ]
        for topic, stamp, received, records in clouds:
            messages.append((received, topic, sink.pointcloud(stamp, "os_lidar", records)))
        for received, topic, msg in sorted(messages, key=lambda m: m[0]):
            sink.write(topic, received, msg)
    return path


def _dual_bag(path: Path) -> Path:
    """Three pairs (second 5 ms after its first), then a first without its second, then a
    second whose first is missing."""
    clouds = []
    for k in range(3):
        first, second = _ranges(k)
        t = 1.0 + 0.1 * k
        clouds += [(FIRST, t, t + 0.002, _records(first)), (SECOND, t, t + 0.007, _records(second))]
    clouds.append((FIRST, 1.3, 1.302, _records(_ranges(3)[0])))
    clouds.append((SECOND, 1.45, 1.452, _records(_ranges(4)[1])))
    return _write_bag(path, clouds)


@pytest.fixture(scope="module")
def dual_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _dual_bag(tmp_path_factory.mktemp("dual") / "dual")


def _sorted(mapper: Any) -> tuple[np.ndarray, np.ndarray]:
    v = mapper.voxels()
    order = np.lexsort(v.ijk.T)
    return v.ijk[order], np.stack([v.s[order], v.n[order]])


def _expected(scans: list[tuple[np.ndarray, np.ndarray | None]]) -> tuple[float, float]:
    """Brute force: ``s`` and ``n`` of the pixels' shots, the first return from the sensor,
    the second from the blind stretch behind it (left out when inside it)."""
    s = n = 0.0
    for first, second in scans:
        for i in range(HEIGHT):
            for j in range(WIDTH):
                if first[i, j] <= 0.0:
                    continue
                s, n = s + first[i, j], n + 1
                if second is not None and second[i, j] > 0.0:
                    s += max(0.0, second[i, j] - (first[i, j] + BLIND))
                    n += 1
    return s, n


def test_a_dual_return_bag_maps_both_returns_as_the_node_pairs_them(dual_bag: Path) -> None:
    result = replay(dual_bag, PAIRED, progress=False)
    summary = result.summary
    assert summary.second_return == {
        "paired": 3, "alone": 1, "unpaired_second": 1, "mismatched": 0,
    }  # fmt: skip
    assert summary.scans_used == summary.scans_total == 4
    assert summary.cloud_topic == f"{FIRST} + {SECOND}"
    text = summary.format()
    assert "2nd returns  alone 1, mismatched 0, paired 3, unpaired_second 1" in text
    # the map: every return of a pixel in one shot, checked against brute force
    voxels = result.mapper.voxels()
    scans = [_ranges(k) for k in range(3)] + [(_ranges(3)[0], None)]
    want_s, want_n = _expected(scans)  # type: ignore[arg-type]
    assert float(np.sum(voxels.n, dtype=np.float64)) == want_n
    assert float(np.sum(voxels.s, dtype=np.float64)) == pytest.approx(want_s, rel=1e-5)
    # the same map as the node's loop fed the same pairs by its pairer (the node's path)
    node_map = new_mapper(PAIRED, "odom")
    loop = ScanLoop(node_map, PAIRED.placement, PAIRED.sensor_model)
    pairer = ReturnPairer()
    with open_recording(
        dual_bag, OPTS.but(cloud_topic=FIRST)
    ) as plain:  # no pairing: the raw first clouds
        firsts = [c.load() for c in plain.clouds()]
        poses = plain.pose_source
    with open_recording(dual_bag, OPTS.but(cloud_topic=SECOND)) as seconds_only:
        seconds = [c.load() for c in seconds_only.clouds()]
    ready = []
    for first, second in zip(firsts[:3], seconds[:3], strict=True):
        ready += pairer.first(first, 0.0) + pairer.second(second, 0.0)
    ready += pairer.first(firsts[3], 0.0) + pairer.second(seconds[3], 0.0) + pairer.flush()
    assert [isinstance(r, ReturnPair) for r in ready] == [True, True, True, False]
    for msg in ready:
        assert loop.map_cloud(msg, poses, lambda _frame: Extrinsic()).integrated
    assert pairer.counts() == summary.second_return
    ijk, sn = _sorted(result.mapper)
    node_ijk, node_sn = _sorted(node_map)
    np.testing.assert_array_equal(ijk, node_ijk)
    np.testing.assert_array_equal(sn, node_sn)
    # without the setting, the first returns alone (as before): fewer returns
    alone = replay(dual_bag, OPTS.but(cloud_topic=FIRST), progress=False)
    assert alone.summary.second_return is None
    first_n = float(np.sum(alone.mapper.voxels().n, dtype=np.float64))
    assert first_n == _expected([(f, None) for f, _ in scans])[1] < want_n


def test_the_second_topic_is_not_a_cloud_topic_candidate(dual_bag: Path) -> None:
    with open_recording(dual_bag, PAIRED) as recording:
        assert recording.cloud_source == f"{FIRST} + {SECOND}"
        assert recording.cloud_count == 4
        clouds = list(recording.clouds())
        assert sorted(c.position for c in clouds) == [0, 1, 2, 3]
        loaded = [c.load() for c in clouds]
        assert [isinstance(m, ReturnPair) for m in loaded] == [True, True, True, False]
        pairer = recording.second_returns()
        assert pairer is not None and pairer.counts()["paired"] == 3
    with pytest.raises(ReplayError, match="several PointCloud2 topics.*--second-return-topic"):
        replay(dual_bag, OPTS, progress=False)
    with pytest.raises(ReplayError, match="second_return_topic '/lidar/points2' is not"):
        replay(dual_bag, OPTS.but(second_return_topic="/lidar/points2"), progress=False)
    with pytest.raises(ReplayError, match="both the cloud and the second-return topic"):
        replay(dual_bag, PAIRED.but(cloud_topic=SECOND), progress=False)
    # the node's relative name resolves in the root namespace
    relative = OPTS.but(second_return_topic="ouster/points2")
    assert replay(dual_bag, relative, progress=False).summary.second_return is not None


def test_a_second_cloud_without_its_first_and_a_first_whose_second_came_late(
    tmp_path: Path,
) -> None:
    """A second cloud more than 0.2 s (receive time) after its first: the first was mapped
    alone, as the node's timer does; the second is counted unpaired, nothing else lost."""
    first, second = _ranges(0)
    bag = _write_bag(
        tmp_path / "late",
        [(FIRST, 1.0, 1.0, _records(first)), (SECOND, 1.0, 1.5, _records(second)),
         (SECOND, 2.0, 2.0, _records(second))],
    )  # fmt: skip
    result = replay(bag, PAIRED, progress=False)
    assert result.summary.second_return == {
        "paired": 0, "alone": 1, "unpaired_second": 2, "mismatched": 0,
    }  # fmt: skip
    assert float(np.sum(result.mapper.voxels().n, dtype=np.float64)) == (first > 0).sum()


def test_mismatched_layouts_map_the_first_returns_and_say_why(tmp_path: Path) -> None:
    first, _ = _ranges(0)
    narrow = np.full((HEIGHT, WIDTH // 2), 7.0)
    bag = _write_bag(
        tmp_path / "mismatch",
        [(FIRST, 1.0, 1.0, _records(first)), (SECOND, 1.0, 1.001, _records(narrow, WIDTH // 2))],
    )
    said: list[str] = []
    result = replay(bag, PAIRED, progress=False, log=said.append)
    summary = result.summary
    assert summary.second_return == {
        "paired": 0, "alone": 1, "unpaired_second": 0, "mismatched": 1,
    }  # fmt: skip
    assert "second-return cloud of 4 x 16 points for a first-return cloud of 4 x 32" in (
        summary.second_return_note
    )
    assert any("not paired" in line for line in said)
    assert summary.second_return_note in summary.format()
    # nothing lost: the first returns mapped as without the second topic
    plain = replay(bag, OPTS.but(cloud_topic=FIRST), progress=False)
    for got, want in zip(_sorted(result.mapper), _sorted(plain.mapper), strict=True):
        np.testing.assert_array_equal(got, want)


def test_the_replay_command_pairs_with_the_flag_or_the_node_yaml(
    dual_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    from mfp_mapper.cli import main

    out, summary = tmp_path / "map.npz", tmp_path / "summary.json"
    argv = ["replay", str(dual_bag), "-o", str(out), "--resolution", "0.25", "-q"]
    assert main([*argv, "--second-return-topic", SECOND, "--summary-json", str(summary)]) == 0
    assert "2nd returns  alone 1, mismatched 0, paired 3" in capsys.readouterr().out
    assert json.loads(summary.read_text())["second_return"]["paired"] == 3
    robot = tmp_path / "robot.yaml"  # the node's parameter file, as docs/robot.md has it
    robot.write_text(f"/**:\n  ros__parameters:\n    second_return_topic: {SECOND}\n")
    assert main([*argv, "--config", str(robot)]) == 0
    assert "paired 3" in capsys.readouterr().out
    assert main(argv) == 1  # two cloud topics and no flag: the error names the flag
    assert "--second-return-topic /ouster/points2" in capsys.readouterr().err


def test_score_scores_the_second_returns_as_later_echoes(dual_bag: Path, tmp_path: Path) -> None:
    import json

    from mfp_mapper.cli import main

    def echoes(*flags: str) -> Any:
        out = tmp_path / "score.json"
        argv = ["score", str(dual_bag), "--split", "shots", "--resolution", "0.25", "-q"]
        assert main([*argv, "--no-classic", "--json", str(out), *flags]) == 0
        return json.loads(out.read_text()).get("echoes")

    paired = echoes("--second-return-topic", SECOND)
    # the held-out shots' second returns are scored as later echoes
    assert paired["all"]["later_echoes"] > 0
    assert paired["all"]["first_echoes"] == paired["first_only"]["first_echoes"] > 0
    assert echoes("--cloud-topic", FIRST) is None  # the first returns alone: no echoes
