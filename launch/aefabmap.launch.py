"""Launch feature, quantizer and FAB-MAP nodes (full ROS 2 Jazzy install; pip users: aefabmap_launch).

    ros2 launch aefabmap_ros aefabmap.launch.py model_dir:=/path/to/model image_topic:=/camera/image_raw
    # also verify the loop closures geometrically (verified_loop_closures)
    ros2 launch aefabmap_ros aefabmap.launch.py model_dir:=/path/to/model verify:=true
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    model_dir = LaunchConfiguration("model_dir")
    params_file = LaunchConfiguration("params_file")
    map_file = LaunchConfiguration("map_file")
    image_topic = LaunchConfiguration("image_topic")
    image_qos = LaunchConfiguration("image_qos")
    common = [params_file, {"model_dir": model_dir}]
    return LaunchDescription([
        DeclareLaunchArgument("model_dir", description="model directory made by aefabmap_train"),
        DeclareLaunchArgument(
            "params_file",
            default_value=PathJoinSubstitution([FindPackageShare("aefabmap_ros"), "config", "aefabmap.yaml"]),
            description="parameter YAML for the three nodes",
        ),
        DeclareLaunchArgument("map_file", default_value="", description="map file to save to / reload from"),
        DeclareLaunchArgument("image_topic", default_value="image", description="camera image topic"),
        DeclareLaunchArgument("image_qos", default_value="sensor_data", description="sensor_data or reliable"),
        DeclareLaunchArgument("verify", default_value="false",
                              description="also run verifier_node (geometric verification -> verified_loop_closures)"),
        Node(package="aefabmap_ros", executable="feature_node", name="feature_node",
             parameters=[*common, {"image_qos": image_qos}], remappings=[("image", image_topic)], output="screen"),
        Node(package="aefabmap_ros", executable="quantizer_node", name="quantizer_node",
             parameters=common, output="screen"),
        Node(package="aefabmap_ros", executable="fabmap_node", name="fabmap_node",
             parameters=[*common, {"map_file": map_file}], output="screen"),
        Node(package="aefabmap_ros", executable="verifier_node", name="verifier_node",
             parameters=[params_file], output="screen", condition=IfCondition(LaunchConfiguration("verify"))),
    ])
