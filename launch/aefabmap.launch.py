"""Launch the loop-closure nodes (full ROS 2 Jazzy install; pip users: aefabmap_launch).

    ros2 launch aefabmap_ros aefabmap.launch.py model_dir:=/path/to/model image_topic:=/camera/image_raw
    # without geometric verification: FAB-MAP's raw closures on loop_closures (inliers -1)
    ros2 launch aefabmap_ros aefabmap.launch.py model_dir:=/path/to/model verify:=false
    # with the closure pictures (closure_view_node), for foxglove_bridge or rqt_image_view
    ros2 launch aefabmap_ros aefabmap.launch.py model_dir:=/path/to/model pictures:=true
    # several robots (docs/fleet.md): each robot's front end, and the base station
    ros2 launch aefabmap_ros aefabmap.launch.py model_dir:=/path/to/model robot_side:=true robot:=robot1
    ros2 launch aefabmap_ros aefabmap.launch.py model_dir:=/path/to/model base:=true robots:=robot1,robot2

The nodes, their parameters and remaps come from ``aefabmap_ros.nodes.launch_table``, the same table
``aefabmap_launch`` uses: by default verifier_node runs and ``loop_closures`` carries only
geometrically verified closures (FAB-MAP's raw ones: ``loop_closure_candidates``).
"""

import os
from typing import Any

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from aefabmap_ros.nodes.launch_table import (
    PACKAGE,
    SuiteOptions,
    namespaced_sections,
    parse_bool,
    parse_robots,
    suite_nodes,
    thread_limits,
)


def _nodes(context: Any) -> list[Node]:
    def value(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    options = SuiteOptions(model_dir=value("model_dir"), map_file=value("map_file"), robot=value("robot"),
                           image_topic=value("image_topic"), image_qos=value("image_qos"),
                           verify=parse_bool(value("verify"), "verify"),
                           backend=parse_bool(value("backend"), "backend"),
                           pictures=parse_bool(value("pictures"), "pictures"),
                           camera_info_topic=value("camera_info_topic"), depth_topic=value("depth_topic"),
                           odom_topic=value("odom_topic"), closures_topic=value("closures_topic"),
                           sensor_qos=value("sensor_qos"), robot_side=parse_bool(value("robot_side"), "robot_side"),
                           base=parse_bool(value("base"), "base"),
                           robots=tuple(parse_robots(value("robots"), "robots")))
    params_file = value("params_file")
    nodes = suite_nodes(options)
    # Each process's share of the cores for torch/OpenBLAS/numba pools, unless the user set them.
    limits = thread_limits(len(nodes), os.environ)
    return [
        Node(package=PACKAGE, executable=node.name, name=node.name, namespace=node.namespace or None,
             parameters=[_params_for(params_file, node.namespace), dict(node.parameters)],
             remappings=list(node.remaps.items()), additional_env=limits, output="screen")
        for node in nodes
    ]


def _params_for(params_file: str, namespace: str) -> str:
    """The parameter file, its sections renamed for nodes in ``namespace`` (rcl matches a node's full name)."""
    if not namespace:
        return params_file
    import tempfile

    import yaml

    with open(params_file) as source:
        content = yaml.safe_load(source) or {}
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", prefix="aefabmap_", delete=False) as copy:
        yaml.safe_dump(namespaced_sections(content, namespace), copy)
    return copy.name


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("model_dir", description="model directory made by aefabmap_train"),
        DeclareLaunchArgument(
            "params_file",
            default_value=PathJoinSubstitution([FindPackageShare(PACKAGE), "config", "aefabmap.yaml"]),
            description="parameter YAML of the nodes",
        ),
        DeclareLaunchArgument("map_file", default_value="",
                              description="map file to save to / reload from (the verifier's features beside it)"),
        DeclareLaunchArgument("robot", default_value="",
                              description="this robot's name, kept with its sessions of the map ('' = one robot)"),
        DeclareLaunchArgument("image_topic", default_value="image", description="camera image topic"),
        DeclareLaunchArgument("image_qos", default_value="",
                              description="auto, best_effort or reliable ('' = the parameter file's)"),
        DeclareLaunchArgument("camera_info_topic", default_value="",
                              description="CameraInfo topic ('' = beside image_topic, image_transport's convention)"),
        DeclareLaunchArgument("depth_topic", default_value="",
                              description="aligned depth image topic ('' = the parameter file's depth_topic)"),
        DeclareLaunchArgument("odom_topic", default_value="", description="odometry topic ('' = odom)"),
        DeclareLaunchArgument("closures_topic", default_value="",
                              description="topic of the verified loop closures ('' = loop_closures)"),
        DeclareLaunchArgument("sensor_qos", default_value="",
                              description="auto, best_effort or reliable for camera_info, depth and odometry "
                              "('' = the parameter file's)"),
        DeclareLaunchArgument("verify", default_value="true",
                              description="run verifier_node: only geometrically verified closures on loop_closures; "
                              "false: FAB-MAP's raw closures on loop_closures (inliers -1)"),
        DeclareLaunchArgument("backend", default_value="false",
                              description="also run pose_graph_node, the example SLAM backend (odometry on odom)"),
        DeclareLaunchArgument("pictures", default_value="false",
                              description="also run closure_view_node: each closure as a picture on "
                              "closure_view/closures (drawn only while subscribed; Foxglove's own bridge serves it)"),
        DeclareLaunchArgument("robot_side", default_value="false",
                              description="a robot's front end for a base station, in namespace /<robot>: "
                              "feature_node, quantizer_node and feature_server_node (docs/fleet.md)"),
        DeclareLaunchArgument("base", default_value="false",
                              description="the base station of robots: one map, the verifier asking the robots for "
                              "features, with backend:=true the example backend"),
        DeclareLaunchArgument("robots", default_value="",
                              description="with base:=true, the robots (comma-separated), each under /<robot>"),
        OpaqueFunction(function=_nodes),
    ])
