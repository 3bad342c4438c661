"""Launch the odometry node with config/odometry.yaml.

    ros2 launch nocal_ros odometry.launch.py image:=/camera/image_raw
    ros2 launch nocal_ros odometry.launch.py image:=/cam/image_raw model_path:=~/.ros/nocal_ros/models
    ros2 launch nocal_ros odometry.launch.py camera_info_url:=file:///data/wrist.yaml use_sim_time:=true
    ros2 launch nocal_ros odometry.launch.py arm_pose_source:=pose arm_pose:=/arm/pose
    ros2 launch nocal_ros odometry.launch.py ground_frame:=base_footprint    # metric scale from the floor

The arguments below override the same parameters in params_file; the others come from params_file.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory("nocal_ros"), "config", "odometry.yaml")
    arguments = [
        DeclareLaunchArgument("params_file", default_value=default_params, description="odometry parameters"),
        DeclareLaunchArgument("image", default_value="/camera/image_raw", description="image topic to subscribe to"),
        DeclareLaunchArgument("model_path", default_value="", description="checkpoint or model store ('' = shipped)"),
        DeclareLaunchArgument("device", default_value="auto", description="auto, cpu or cuda"),
        DeclareLaunchArgument("base_frame", default_value="base_link", description="child frame of odom"),
        DeclareLaunchArgument("camera_name", default_value="camera", description="camera_info_manager's ${NAME}"),
        DeclareLaunchArgument("camera_info_url", default_value="",
                              description="calibration YAML (file:// or package://; '' = file://${ROS_HOME}/camera_info/${NAME}.yaml)"),
        DeclareLaunchArgument("arm_pose_source", default_value="none", description="none | pose | tf (arm poses for metric scale)"),
        DeclareLaunchArgument("arm_pose", default_value="/arm/pose", description="PoseStamped arm pose topic (arm_pose_source pose)"),
        DeclareLaunchArgument("ground_frame", default_value="",
                              description="a frame on the ground beneath the camera, z up (base_footprint): TF gives its height"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="follow /clock (ros2 bag play --clock)"),
    ]
    node = Node(
        package="nocal_ros",
        executable="odometry_node",
        name="odometry_node",
        output="screen",
        parameters=[
            LaunchConfiguration("params_file"),
            {  # typed as strings: an empty model_path must stay "" (the shipped model), not None
                "model_path": ParameterValue(LaunchConfiguration("model_path"), value_type=str),
                "device": ParameterValue(LaunchConfiguration("device"), value_type=str),
                "base_frame": ParameterValue(LaunchConfiguration("base_frame"), value_type=str),
                "camera_name": ParameterValue(LaunchConfiguration("camera_name"), value_type=str),
                "camera_info_url": ParameterValue(LaunchConfiguration("camera_info_url"), value_type=str),
                "arm_pose_source": ParameterValue(LaunchConfiguration("arm_pose_source"), value_type=str),
                "ground_frame": ParameterValue(LaunchConfiguration("ground_frame"), value_type=str),
                "use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool),
            },
        ],
        remappings=[
            ("image", LaunchConfiguration("image")),
            ("image/compressed", [LaunchConfiguration("image"), "/compressed"]),
            ("arm_pose", LaunchConfiguration("arm_pose")),
        ],
    )
    return LaunchDescription([*arguments, node])
