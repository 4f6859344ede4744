"""Example ROS 2 launch for a Nav2 + PX4 drone localized by macroloc (docs/ros2.md). Not run by this project's tests:
a sketch to adapt (paths, namespaces). Order: the rmw_zenoh router, macroloc (waits until its first status on
/drone1/macroloc/status: the readiness signal), then Nav2 with its map -> odom from macroloc (no AMCL), and rviz.

    RMW_IMPLEMENTATION=rmw_zenoh_cpp ros2 launch nav2_px4.launch.py
"""

from launch import LaunchDescription
from launch.actions import ExecuteProcess, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch_ros.actions import Node

CONFIG = "/opt/site/macroloc_px4.toml"


def generate_launch_description() -> LaunchDescription:
    router = ExecuteProcess(cmd=["ros2", "run", "rmw_zenoh_cpp", "rmw_zenohd"], output="screen")
    macroloc = ExecuteProcess(cmd=["macroloc", "serve", "--config", CONFIG], output="screen")
    # readiness: the first DiagnosticArray comes once the model is loaded and every input is taken
    ready = ExecuteProcess(cmd=["ros2", "topic", "echo", "--once", "/drone1/macroloc/status",
                                "diagnostic_msgs/msg/DiagnosticArray"], output="log")
    nav2 = [
        # Nav2 without AMCL or map_server's localization: macroloc publishes map -> odom on /tf, PX4's VIO
        # (or px4_ros_com's odometry bridge) odom -> base_link
        Node(package="nav2_controller", executable="controller_server", parameters=["nav2_params.yaml"]),
        Node(package="nav2_planner", executable="planner_server", parameters=["nav2_params.yaml"]),
        Node(package="nav2_bt_navigator", executable="bt_navigator", parameters=["nav2_params.yaml"]),
        Node(package="nav2_lifecycle_manager", executable="lifecycle_manager", name="lifecycle_manager_navigation",
             parameters=[{"autostart": True,
                          "node_names": ["controller_server", "planner_server", "bt_navigator"]}]),
        Node(package="rviz2", executable="rviz2"),  # "2D Pose Estimate" -> /initialpose -> macroloc's prior
    ]
    return LaunchDescription([
        router, macroloc, ready,
        RegisterEventHandler(OnProcessExit(target_action=ready, on_exit=nav2)),
    ])
