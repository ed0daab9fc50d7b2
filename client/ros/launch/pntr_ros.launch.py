"""Launch pntr-ros beside a ROS 2 robot (for teams that have ROS 2 installed; pntr-ros itself needs
none). pntr-ros is a plain executable, not a ROS package, so it is started as a process:

    ros2 launch client/ros/launch/pntr_ros.launch.py addr:=192.168.1.10:50051 namespace:=/robot1

Arguments: addr (pntr-server HOST:PORT), map_id, namespace, params_file (ROS 2 parameter file,
default client/ros/config/pntr_ros.yaml), binary (path of pntr-ros, default `pntr-ros` on PATH).
Set RMW_IMPLEMENTATION as for every other node of the robot: it tells pntr-ros which wire format
the relocalize service's clients use.
"""
import os

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration

HERE = os.path.dirname(os.path.abspath(__file__))


def generate_launch_description():
    arg = LaunchConfiguration
    return LaunchDescription([
        DeclareLaunchArgument("addr", default_value="127.0.0.1:50051"),
        DeclareLaunchArgument("map_id", default_value=""),
        DeclareLaunchArgument("namespace", default_value="/"),
        DeclareLaunchArgument("params_file", default_value=os.path.join(HERE, "..", "config", "pntr_ros.yaml")),
        DeclareLaunchArgument("binary", default_value="pntr-ros"),
        ExecuteProcess(
            cmd=[arg("binary"), "--addr", arg("addr"), "--map-id", arg("map_id"),
                 "--ros-args", "-r", ["__ns:=", arg("namespace")], "--params-file", arg("params_file")],
            output="screen",
            sigterm_timeout="5",
        ),
    ])
