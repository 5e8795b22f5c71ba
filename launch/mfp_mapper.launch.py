"""Launch the mfp_mapper node with its default parameter file.

ros2 launch mfp_mapper mfp_mapper.launch.py cloud_topic:=/velodyne_points odom_topic:=/odom
ros2 launch mfp_mapper mfp_mapper.launch.py params_file:=/path/to/my_params.yaml
ros2 launch mfp_mapper mfp_mapper.launch.py rviz:=true   (also starts RViz with config/mfp_mapper.rviz)
ros2 launch mfp_mapper mfp_mapper.launch.py autostart:=false   (for Nav2's lifecycle manager)
ros2 launch mfp_mapper mfp_mapper.launch.py node_name:=octomap_server octomap_topics:=true \
    params_file:=/path/to/octomap_server.yaml   (where octomap_server stood)

The node gets Fast DDS's large-data profile (config/fastdds_large_data.xml) in its
environment unless large_data_profile:=false, another profile is already exported, or
RMW_IMPLEMENTATION is not Fast DDS (``mfp_mapper.ros.transport.node_environment``). The
lidar driver's process needs the same profile: docs/robot.md, "The DDS profile for large
clouds".
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, LogInfo, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchContext, LaunchDescription

TRUE = ("true", "1", "yes", "on")


def _mapper(context: LaunchContext) -> list:
    """The mapper node, its environment built from the resolved arguments."""
    from mfp_mapper.ros.transport import PROFILE_FILE, node_environment

    def arg(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    share = get_package_share_directory("mfp_mapper")
    profile = os.path.join(share, "config", PROFILE_FILE)
    env, why = node_environment(
        os.environ, profile, arg("large_data_profile").lower() in TRUE
    )
    return [
        LogInfo(msg=f"mfp_mapper: {why}"),
        Node(
            package="mfp_mapper",
            executable="mfp_mapper",
            name=arg("node_name"),
            output="screen",
            additional_env=env,
            parameters=[
                arg("params_file"),
                {
                    "use_sim_time": arg("use_sim_time").lower() in TRUE,
                    "autostart": arg("autostart").lower() in TRUE,
                    "octomap_topics": arg("octomap_topics").lower() in TRUE,
                },
            ],
            remappings=[
                ("cloud_in", arg("cloud_topic")),
                ("odom", arg("odom_topic")),
            ],
        ),
    ]


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("mfp_mapper")
    default_params = os.path.join(share, "config", "mfp_mapper.yaml")
    default_rviz = os.path.join(share, "config", "mfp_mapper.rviz")
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file", default_value=default_params, description="ROS parameter file"
            ),
            DeclareLaunchArgument(
                "cloud_topic", default_value="cloud_in", description="sensor_msgs/PointCloud2 in"
            ),
            DeclareLaunchArgument(
                "odom_topic", default_value="odom", description="nav_msgs/Odometry in"
            ),
            DeclareLaunchArgument(
                "use_sim_time", default_value="false", description="Use /clock (bag replay)"
            ),
            DeclareLaunchArgument(
                "node_name",
                default_value="mfp_mapper",
                description="Node name (octomap_server: its parameter files apply unchanged)",
            ),
            DeclareLaunchArgument(
                "autostart",
                default_value="true",
                description="Configure and activate at start; false: wait for a lifecycle manager",
            ),
            DeclareLaunchArgument(
                "octomap_topics",
                default_value="false",
                description="Publish projected_map and octomap_point_cloud_centers as "
                "octomap_server does",
            ),
            DeclareLaunchArgument(
                "large_data_profile",
                default_value="true",
                description="Give the node Fast DDS's large-data profile "
                "(config/fastdds_large_data.xml); false: Fast DDS defaults",
            ),
            DeclareLaunchArgument(
                "rviz", default_value="false", description="Also start RViz (rviz2)"
            ),
            DeclareLaunchArgument(
                "rviz_config", default_value=default_rviz, description="RViz config file"
            ),
            OpaqueFunction(function=_mapper),
            Node(
                package="rviz2",
                executable="rviz2",
                name="rviz2",
                output="log",
                arguments=["-d", LaunchConfiguration("rviz_config")],
                parameters=[{"use_sim_time": LaunchConfiguration("use_sim_time")}],
                condition=IfCondition(LaunchConfiguration("rviz")),
            ),
        ]
    )
