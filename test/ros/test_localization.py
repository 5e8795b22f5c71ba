"""The localization role's rules that need no DDS: the map frame it localizes in and the stamp
a new correction is published at (issue 32 items 4 and 6)."""

from __future__ import annotations

import math

from mfp_mapper.ros.localization import localization_frame, tf_stamp


def test_the_map_frame_is_never_the_odometry_frame_by_default() -> None:
    assert localization_frame("", "odom", "odom") == "map"  # a map made by replay
    assert localization_frame("", "", "odom") == "map"
    assert localization_frame("", "world", "odom") == "world"  # the map's own frame
    assert localization_frame("site", "odom", "odom") == "site"  # frame_id wins
    assert localization_frame("odom", "odom", "odom") == "odom"  # refused by the node


def test_a_late_correction_is_stamped_at_the_clock() -> None:
    now, tol = 1000.0, 0.5
    assert tf_stamp(999.8, now, tol, -math.inf) == 999.8  # on time: its cloud's stamp
    assert tf_stamp(989.0, now, tol, -math.inf) == now - tol  # 11 s late: valid at once
    assert tf_stamp(999.8, now, tol, 999.9) == 999.9  # never before the last one published
    assert tf_stamp(10.0, 12.0, tol, 999.9) == 12.0  # the clock jumped back: at the clock
    assert tf_stamp(5.0, 0.0, tol, -math.inf) == 5.0  # sim time before /clock
