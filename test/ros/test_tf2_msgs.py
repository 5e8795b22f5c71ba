"""tf2_msgs built by ``./run setup`` (scripts/build_interface.sh): same type as real Jazzy."""

from __future__ import annotations

import pytest
from ros_helpers import domain_id, set_ros_env

# Type hash of tf2_msgs/msg/TFMessage in ROS 2 Jazzy (RIHS01, REP 2011).
JAZZY_TFMESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"

pytestmark = pytest.mark.ros


def test_rosbags_jazzy_typestore_agrees_on_the_hash() -> None:
    typesys = pytest.importorskip("rosbags.typesys")
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    assert store.hash_rihs01("tf2_msgs/msg/TFMessage") == JAZZY_TFMESSAGE_HASH


def test_built_tfmessage_has_the_jazzy_type_hash_on_the_wire() -> None:
    """The hash the middleware announces for a /tf publisher is real Jazzy's."""
    rclpy = pytest.importorskip("rclpy")
    from tf2_msgs.msg import TFMessage  # noqa: PLC0415  (built by ./run setup)

    set_ros_env(domain_id())
    context = rclpy.context.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("tf2_msgs_hash_check", context=context)
        node.create_publisher(TFMessage, "/tf", 10)
        infos = node.get_publishers_info_by_topic("/tf")
        assert len(infos) == 1
        assert infos[0].topic_type == "tf2_msgs/msg/TFMessage"
        assert str(infos[0].topic_type_hash) == JAZZY_TFMESSAGE_HASH
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_tfmessage_holds_transforms() -> None:
    pytest.importorskip("rclpy")
    from geometry_msgs.msg import TransformStamped  # noqa: PLC0415
    from tf2_msgs.msg import TFMessage  # noqa: PLC0415

    msg = TFMessage(transforms=[TransformStamped(child_frame_id="lidar")])
    assert msg.transforms[0].child_frame_id == "lidar"
