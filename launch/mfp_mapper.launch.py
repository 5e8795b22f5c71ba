"""Launch the mfp_mapper node with its default parameter file.

ros2 launch mfp_mapper mfp_mapper.launch.py cloud_topic:=/velodyne_points odom_topic:=/odom
ros2 launch mfp_mapper mfp_mapper.launch.py params_file:=/path/to/my_params.yaml
ros2 launch mfp_mapper mfp_mapper.launch.py rviz:=true   (also starts RViz with config/mfp_mapper.rviz)
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


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
                "rviz", default_value="false", description="Also start RViz (rviz2)"
            ),
            DeclareLaunchArgument(
                "rviz_config", default_value=default_rviz, description="RViz config file"
            ),
            Node(
                package="mfp_mapper",
                executable="mfp_mapper",
                name="mfp_mapper",
                output="screen",
                parameters=[
                    LaunchConfiguration("params_file"),
                    {"use_sim_time": LaunchConfiguration("use_sim_time")},
                ],
                remappings=[
                    ("cloud_in", LaunchConfiguration("cloud_topic")),
                    ("odom", LaunchConfiguration("odom_topic")),
                ],
            ),
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
