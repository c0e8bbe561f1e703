"""The launch table's two ends of a robot's link to a base station (docs/fleet.md), and aefabmap_launch's
commands for them."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml

from aefabmap_ros.cli import launch
from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.launch_table import NodeLaunch, SuiteOptions, namespaced_sections, parse_robots, suite_nodes


def _by_name(options: SuiteOptions) -> dict[str, NodeLaunch]:
    return {node.name: node for node in suite_nodes(options)}


def test_the_robot_side_runs_the_front_end_and_the_feature_server_in_the_robots_namespace() -> None:
    nodes = _by_name(SuiteOptions(model_dir="/m", robot="robot1", robot_side=True, image_topic="/cam/image_raw",
                                  depth_topic="/cam/depth", image_qos="best_effort", odom_topic="/odometry/filtered"))
    assert list(nodes) == ["feature_node", "quantizer_node", "feature_server_node"]
    assert {node.namespace for node in nodes.values()} == {"/robot1"}
    assert nodes["feature_node"].remaps == {"image": "/cam/image_raw"}
    assert nodes["quantizer_node"].remaps == {"quantizer_node:aefabmap/words": "aefabmap/robot_words"}
    assert nodes["feature_server_node"].parameters == {"robot": "robot1", "depth_topic": "/cam/depth"}
    assert nodes["feature_server_node"].remaps == {"camera_info": "/cam/camera_info", "odom": "/odometry/filtered"}


def test_the_base_runs_one_map_and_the_verifier_for_every_robot() -> None:
    nodes = _by_name(SuiteOptions(model_dir="/m", base=True, robots=("robot1", "robot2"), backend=True,
                                  map_file="/maps/o.npz"))
    assert list(nodes) == ["fabmap_node", "verifier_node", "pose_graph_node"]
    assert nodes["fabmap_node"].parameters["robots"] == nodes["verifier_node"].parameters["robots"] \
        == "[robot1,robot2]"
    assert nodes["verifier_node"].parameters["store_dir"] == "/maps/o.features"
    assert nodes["pose_graph_node"].parameters["robot"] == "robot1"
    assert nodes["pose_graph_node"].parameters["robots"] == "[robot1,robot2]"  # each /<robot>/aefabmap/odom
    assert nodes["pose_graph_node"].remaps == {}
    assert all(not node.namespace for node in nodes.values())
    raw = _by_name(SuiteOptions(model_dir="/m", base=True, robots=("robot1",), verify=False))
    assert list(raw) == ["fabmap_node"] and raw["fabmap_node"].remaps == {"loop_closure_candidates": "loop_closures"}


@pytest.mark.parametrize(("options", "message"), [
    (SuiteOptions(model_dir="/m", robot_side=True), "needs --robot"),
    (SuiteOptions(model_dir="/m", base=True), "needs --robots"),
    (SuiteOptions(model_dir="/m", robots=("a",)), "give --base too"),
    (SuiteOptions(model_dir="/m", robot="a", robot_side=True, base=True, robots=("a",)), "one of them per host"),
    (SuiteOptions(model_dir="/m", robot="a", robot_side=True, map_file="/o.npz"), "base station's"),
    (SuiteOptions(model_dir="/m", base=True, robots=("a",), pictures=True), "stay on the robots"),
])
def test_a_fleet_choice_that_cannot_work_is_refused_by_name(options: SuiteOptions, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        suite_nodes(options)


def test_robot_names_are_namespace_tokens_named_once() -> None:
    assert parse_robots("robot1, robot2", "--robots") == ["robot1", "robot2"]
    assert parse_robots("[robot1,robot2]", "robots") == ["robot1", "robot2"]
    assert parse_robots(["a"], "robots") == ["a"] and parse_robots("", "robots") == parse_robots([], "r") == []
    for bad in ("robot-1", "1robot", "a,a", "a,,b"):
        with pytest.raises(ConfigError):
            parse_robots(bad, "--robots")


def test_a_namespaced_node_gets_the_parameter_files_sections_under_its_full_name() -> None:
    content = {"feature_node": {"ros__parameters": {"x": 1}}, "/**": {"ros__parameters": {"y": 2}}}
    assert namespaced_sections(content, "/robot1") == {"/robot1/feature_node": {"ros__parameters": {"x": 1}},
                                                      "/**": {"ros__parameters": {"y": 2}}}


def test_aefabmap_launch_robot_side_in_one_process_and_the_base(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text("feature_node:\n  ros__parameters:\n    detection_rate_hz: 5.0\n")
    parser = launch.build_parser()
    (robot,) = launch.node_commands(parser.parse_args(["--model", "/m", "--robot-side", "--robot", "robot1",
                                                       "--pipeline", "--params", str(params)]))
    assert robot[:3] == [sys.executable, "-m", "aefabmap_ros.nodes.robot_pipeline"]
    assert "quantizer_node:aefabmap/words:=aefabmap/robot_words" in robot and "__ns:=/robot1" in robot
    copied = Path(robot[robot.index("--params-file") + 1])
    assert yaml.safe_load(copied.read_text()) == {"/robot1/feature_node": {"ros__parameters":
                                                                           {"detection_rate_hz": 5.0}}}
    base = launch.node_commands(parser.parse_args(["--model", "/m", "--base", "--robots", "robot1,robot2",
                                                   "--pipeline", "--params", str(params)]))
    assert [command[2] for command in base] == ["aefabmap_ros.nodes.fabmap_node", "aefabmap_ros.nodes.verifier_node"]
    assert all("robots:=[robot1,robot2]" in command for command in base)
