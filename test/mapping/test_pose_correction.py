"""How the live worker's scans reach the map frame (mapping.pose_correction): mapping places
them there itself; localization moves them by the localizer's correction map <- odom."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from mfp_mapper.config.sections import LocalizationSection
from mfp_mapper.mapping.live_localization import LiveLocalizer, pose_matrix
from mfp_mapper.mapping.pose_correction import LocalizerCorrection, NoCorrection

POINTS = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 0.0]])


def test_mapping_places_in_the_map_frame_and_corrects_nothing() -> None:
    correction = NoCorrection()
    assert (correction.aligns, correction.integrates, correction.names_map) == (
        False,
        True,
        True,
    )
    assert correction.placement_frame("site") == "site"
    assert correction.map_frame("odom") == "odom"
    assert correction.position(None) is None
    np.testing.assert_array_equal(correction.position(POINTS[0]), POINTS[0])
    asked: list[str] = []

    def to_placement(points: np.ndarray, frame: str) -> np.ndarray:
        asked.append(frame)
        return points + 1.0

    np.testing.assert_array_equal(
        correction.to_map_frame(POINTS, "lidar", to_placement), POINTS + 1
    )
    assert asked == ["lidar"]


def test_localization_moves_odometry_frame_points_by_the_correction() -> None:
    settings = LocalizationSection(odom_frame="/odom", freeze_map=True)
    localizer = LiveLocalizer(settings, "map", log=lambda text: None)
    correction = LocalizerCorrection(localizer)
    assert (correction.aligns, correction.integrates, correction.names_map) == (
        True,
        False,
        False,
    )
    assert correction.placement_frame("map") == "odom"
    assert correction.map_frame("odom") == "map"
    map_base = pose_matrix([2.0, -1.0, 0.0], Rotation.from_euler("z", 30, degrees=True).as_matrix())
    odom_base = pose_matrix([0.5, 0.0, 0.0], np.eye(3))
    quaternion = Rotation.from_matrix(map_base[:3, :3]).as_quat()
    assert localizer.initial_pose(10.0, map_base[:3, 3], quaternion, odom_base)
    m = map_base @ np.linalg.inv(odom_base)  # map <- odom
    expected = POINTS @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(correction.position(POINTS[0]), expected[0], atol=1e-12)
    assert correction.position(None) is None
    asked: list[str] = []

    def to_odom(points: np.ndarray, frame: str) -> np.ndarray:
        asked.append(frame)
        return points

    np.testing.assert_allclose(correction.to_map_frame(POINTS, "/lidar", to_odom), expected)
    assert asked == ["lidar"]
    # points already in the map frame (or with no frame) are not moved, nor looked up
    np.testing.assert_array_equal(correction.to_map_frame(POINTS, "/map", to_odom), POINTS)
    np.testing.assert_array_equal(correction.to_map_frame(POINTS, "", to_odom), POINTS)
    assert asked == ["lidar"]
    localizer.settings = LocalizationSection(freeze_map=False)
    assert correction.integrates
