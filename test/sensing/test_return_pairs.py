"""The pairer of first- and second-return clouds (ouster-ros ``points`` + ``points2``), the
node's and the offline replay's: pairs by stamp in either order, maps a first alone when its
second does not come (pushed out, timed out, end of input), counts every cloud once."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from mfp_mapper.sensing.pipeline import ReturnPair
from mfp_mapper.sensing.return_pairs import PAIR_TIMEOUT, PAIR_WAIT, ReturnPairer


def _cloud(stamp: float, width: int = 8, height: int = 2) -> Any:
    """A real (rosbags) sensor_msgs/PointCloud2 of ``height`` x ``width`` points."""
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_JAZZY).types
    ns = int(round(stamp * 1e9))
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
        frame_id="os_lidar",
    )
    return types["sensor_msgs/msg/PointCloud2"](
        header=header, height=height, width=width, fields=[], is_bigendian=False,
        point_step=0, row_step=0, data=np.zeros(0, np.uint8), is_dense=False,
    )  # fmt: skip


def test_pairs_by_stamp_in_either_order() -> None:
    pairer = ReturnPairer()
    a1, a2, b1, b2 = _cloud(1.0), _cloud(1.0), _cloud(1.1), _cloud(1.1)
    assert pairer.first(a1, 0.0) == []
    (pair,) = pairer.second(a2, 0.0)
    assert isinstance(pair, ReturnPair) and pair.first is a1 and pair.second is a2
    assert pair.header is a1.header
    assert pairer.second(b2, 0.1) == []  # the second may come first
    (pair,) = pairer.first(b1, 0.1)
    assert pair.first is b1 and pair.second is b2
    assert pairer.counts() == {"paired": 2, "alone": 0, "unpaired_second": 0, "mismatched": 0}


def test_a_first_waits_for_newer_clouds_or_the_timeout() -> None:
    pairer = ReturnPairer()
    clouds = [_cloud(1.0 + 0.1 * k) for k in range(PAIR_WAIT + 1)]
    ready = [r for k, c in enumerate(clouds) for r in pairer.first(c, 0.01 * k)]
    assert ready == [clouds[0]]  # pushed out by PAIR_WAIT newer ones: mapped alone
    assert pairer.expired(PAIR_TIMEOUT) == [] and pairer.alone == 1
    assert pairer.expired(0.01 + PAIR_TIMEOUT) == [clouds[1]]
    assert pairer.flush() == [clouds[2]]  # the end of the input
    assert pairer.counts() == {"paired": 0, "alone": 3, "unpaired_second": 0, "mismatched": 0}


def test_seconds_without_a_first_are_counted_and_dropped() -> None:
    pairer = ReturnPairer()
    for k in range(PAIR_WAIT + 1):
        assert pairer.second(_cloud(2.0 + 0.1 * k), 0.0) == []
    assert pairer.unpaired_second == 1
    pairer.unreadable_second()
    assert pairer.flush() == []
    assert pairer.counts()["unpaired_second"] == PAIR_WAIT + 2


def test_a_repeated_stamp_loses_no_cloud_uncounted() -> None:
    pairer = ReturnPairer()
    a, again = _cloud(1.0), _cloud(1.0)
    assert pairer.first(a, 0.0) == []
    assert pairer.first(again, 0.0) == [a]  # the earlier goes alone
    assert pairer.second(_cloud(3.0), 0.0) == [] and pairer.second(_cloud(3.0), 0.0) == []
    assert pairer.counts() == {"paired": 0, "alone": 1, "unpaired_second": 1, "mismatched": 0}


def test_grids_that_differ_are_not_paired_and_the_first_goes_alone() -> None:
    pairer = ReturnPairer()
    first = _cloud(1.0, width=8)
    assert pairer.first(first, 0.0) == []
    assert pairer.second(_cloud(1.0, width=4), 0.0) == [first]
    assert pairer.counts() == {"paired": 0, "alone": 1, "unpaired_second": 0, "mismatched": 1}
    assert "2 x 4 points for a first-return cloud of 2 x 8" in pairer.mismatch_note


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_cloud_is_counted_once(seed: int) -> None:
    """Random arrivals (seconds missing, late, repeated, of another grid): each first cloud
    is given out exactly once, paired or alone; each second is paired or counted."""
    rng = np.random.default_rng(seed)
    pairer = ReturnPairer()
    firsts: list[Any] = []
    seconds = 0
    out: list[Any] = []
    now = 0.0
    for _ in range(200):
        stamp = float(rng.integers(0, 60)) * 0.1  # repeated stamps happen
        arrivals = [("first", _cloud(stamp))]
        if rng.random() < 0.8:
            width = 8 if rng.random() < 0.9 else 4
            arrivals.append(("second", _cloud(stamp, width=width)))
        rng.shuffle(arrivals)  # type: ignore[arg-type]
        for kind, msg in arrivals:
            now += float(rng.exponential(0.05))
            out += pairer.expired(now)
            if kind == "first":
                firsts.append(msg)
                out += pairer.first(msg, now)
            else:
                seconds += 1
                out += pairer.second(msg, now)
    out += pairer.flush()
    given = [r.first if isinstance(r, ReturnPair) else r for r in out]
    assert sorted(map(id, given)) == sorted(map(id, firsts))
    c = pairer.counts()
    assert c["paired"] + c["alone"] == len(firsts)
    assert c["paired"] + c["unpaired_second"] + c["mismatched"] == seconds
    assert sum(isinstance(r, ReturnPair) for r in out) == c["paired"] > 0
