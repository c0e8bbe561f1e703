"""The ``robots`` parameter of the base station's nodes (several robots, docs/fleet.md), and robots' topics.

``robots`` names the robots whose frames a base-station node takes, each under its own namespace
(``/<robot>/aefabmap/words``, ``/<robot>/aefabmap/requested_features``, ...). Empty (the default), the
node takes one robot's topics in its own namespace, as on a single host. A string array in a parameter
file or ``-p robots:=[robot1,robot2]``; a comma-separated string is taken too (a launch argument).
"""

from __future__ import annotations

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.launch_table import parse_robots

FRAMES_OF_ROBOTS = ("Robots whose frames this node takes, each from its own namespace /<robot>/... (several "
                    "robots, docs/fleet.md); [] = one robot, this node's own topics.")


def declare_robots(node: Node, description: str = FRAMES_OF_ROBOTS) -> list[str]:
    """Declare and read ``robots`` (dynamically typed: an empty list in YAML has no element type)."""
    try:
        node.declare_parameter("robots", [], ParameterDescriptor(description=description, dynamic_typing=True))
    except Exception as exc:  # rclpy's parameter exceptions
        raise ConfigError(f"parameter 'robots': {exc}") from exc
    return parse_robots(node.get_parameter("robots").value, f"{node.get_name()}: parameter robots")


def robot_topic(robot: str, topic: str) -> str:
    """A robot's topic, absolute: ``robot_topic('robot1', 'aefabmap/words')`` -> ``/robot1/aefabmap/words``."""
    return f"/{robot}/{topic.lstrip('/')}"
