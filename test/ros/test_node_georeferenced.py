"""A geo-referenced odometry frame over real DDS on loopback (issue 32, item 7): odometry at
UTM coordinates (easting 5e5 m, northing 5.4e6 m) is mapped with the default settings; the
point-cloud band ``point_cloud_min/max_x/y/z`` means "no limit" by default."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from localization_scenes import localization_scene, pose_at, static_scan
from ros_helpers import Feeder, NodeProcess, cloud_from_columns, odom_msg, read_cloud

pytestmark = pytest.mark.ros

UTM = np.array([512_345.6, 5_412_345.7, 250.0])


def test_utm_odometry_is_mapped_with_the_default_band(ros_domain: int, tmp_path: Path) -> None:
    scene, positions = localization_scene("box")
    params = {
        "resolution": 0.2,
        "sensor_model.max_range": 60.0,
        "publish_rate": 2.0,
        "status_period": 0.25,
        "odom_wait": 1.0,
        "deskew": False,
    }
    node = NodeProcess(ros_domain, params, tmp_path / "utm.log")
    feeder = Feeder()
    try:
        assert feeder.wait_connected(30.0), node.log()[-3000:]
        ready = feeder.wait_status(lambda s: s.get("kernels") != "compiling", 300.0)
        assert ready is not None, node.log()[-3000:]
        t = time.time()
        for k in range(4):
            truth = pose_at(positions[k], yaw=0.3 * k)
            stamp = t + 0.2 * k
            for dt in (-0.05, 0.0, 0.05):
                feeder.odom_pub.publish(odom_msg(stamp + dt, truth.translation + UTM, 0.3 * k))
            pts = static_scan(scene, truth, np.random.default_rng(k)).astype(np.float32)
            feeder.cloud_pub.publish(
                cloud_from_columns({a: pts[:, i] for i, a in enumerate("xyz")}, "base_link", stamp)
            )
            feeder.spin(0.2)
        status = feeder.wait_status(lambda s: s["clouds_integrated"] >= 3, 30.0)
        assert status is not None and status["clouds_integrated"] >= 3, (status, node.log()[-3000:])
        assert not status["points_dropped"].get("xy_band"), status["points_dropped"]
        # a publication from before the first integration may be the latched one still
        assert feeder.wait(lambda: feeder.doo is not None and feeder.doo.width > 0, 30.0), (
            node.log()[-3000:]
        )
        cloud = read_cloud(feeder.doo)
        centre = np.array([np.median(cloud[a]) for a in "xyz"])
        assert np.abs(centre[:2] - UTM[:2]).max() < 50.0, centre  # the walls, at UTM
    finally:
        feeder.destroy()
        code = node.stop()
    assert code == 0 and "Traceback" not in node.log(), node.log()[-3000:]
