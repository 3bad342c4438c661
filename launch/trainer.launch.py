"""Launch the trainer node with config/trainer.yaml (override with params_file:=...).

    ros2 launch nocal_ros trainer.launch.py output_store:=/data/models
    ros2 service call /trainer_node/record std_srvs/srv/SetBool "{data: true}"   # record live, then
    ros2 service call /trainer_node/record std_srvs/srv/SetBool "{data: false}"  # stop: ~/start trains on it

Without ROS, ``nocal train --init MODEL --bag BAG --out STORE`` runs the same fine-tuning job.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("nocal_ros")
    default_params = os.path.join(share, "config", "trainer.yaml")
    params_file = LaunchConfiguration("params_file")
    output_store = LaunchConfiguration("output_store")
    reload_service = LaunchConfiguration("reload_service")
    training_config = LaunchConfiguration("training_config")
    use_sim_time = LaunchConfiguration("use_sim_time")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params, description="trainer parameters"),
        DeclareLaunchArgument("output_store", default_value=os.path.expanduser("~/.ros/nocal_ros/models"),
                              description="model store shared with the odometry node's model_path"),
        DeclareLaunchArgument("reload_service", default_value="/odometry_node/reload_model",
                              description="odometry node's reload service (empty: do not call)"),
        DeclareLaunchArgument("training_config", default_value=os.path.join(share, "config", "finetune.yaml"),
                              description="training recipe YAML for fine-tuning"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="follow /clock (the recording's duration limit then runs on it)"),
        Node(
            package="nocal_ros",
            executable="trainer_node",
            name="trainer_node",
            output="screen",
            parameters=[params_file, {"output_store": output_store, "reload_service": reload_service,
                                     "training_config": training_config,
                                     "use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
        ),
    ])
