"""The one table both launchers render: what each node gets beyond the parameter file."""

from __future__ import annotations

import pytest

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.nodes.launch_table import SuiteOptions, camera_info_beside, suite_nodes


def _parameters(options: SuiteOptions, node: str) -> dict[str, str]:
    return next(launch.parameters for launch in suite_nodes(options) if launch.name == node)


@pytest.mark.parametrize(("image_qos", "drop_when_busy"),
                         [("sensor_data", "true"), ("auto", "true"), ("best_effort", "true"), ("reliable", "false")])
def test_the_stages_drop_frames_exactly_when_the_camera_subscription_does(image_qos: str, drop_when_busy: str) -> None:
    """A live camera's frames may be dropped at every stage; a lossless replay must lose none at any."""
    options = SuiteOptions(model_dir="/m", image_qos=image_qos)
    assert _parameters(options, "feature_node")["image_qos"] == image_qos
    assert _parameters(options, "feature_node")["drop_when_busy"] == drop_when_busy
    assert _parameters(options, "quantizer_node")["drop_when_busy"] == drop_when_busy


def test_without_an_image_qos_choice_both_nodes_keep_the_parameter_files_values() -> None:
    options = SuiteOptions(model_dir="/m")
    assert "image_qos" not in _parameters(options, "feature_node")
    assert _parameters(options, "quantizer_node") == {"model_dir": "/m"}


def _remaps(options: SuiteOptions, node: str) -> dict[str, str]:
    return next(launch.remaps for launch in suite_nodes(options) if launch.name == node)


@pytest.mark.parametrize(("image_topic", "camera_info"), [
    ("/camera/rgb/image_raw", "/camera/rgb/camera_info"), ("image", "camera_info"), ("/image", "/camera_info"),
    ("cam/image/", "cam/camera_info")])
def test_camera_info_is_found_beside_the_image_as_image_transport_names_it(image_topic: str, camera_info: str) -> None:
    assert camera_info_beside(image_topic) == camera_info


def test_every_input_and_output_of_a_robot_can_be_renamed() -> None:
    options = SuiteOptions(model_dir="/m", backend=True, image_topic="/camera/rgb/image_raw",
                           depth_topic="/camera/depth_registered/image_raw", odom_topic="/odometry/filtered",
                           closures_topic="/slam/loop_closures", sensor_qos="best_effort",
                           remaps=("place_posteriors:=/lc/posteriors",))
    assert _remaps(options, "feature_node") == {"image": "/camera/rgb/image_raw",
                                                "place_posteriors": "/lc/posteriors"}
    assert _remaps(options, "verifier_node") == {
        "camera_info": "/camera/rgb/camera_info", "odom": "/odometry/filtered",
        "loop_closures": "/slam/loop_closures", "place_posteriors": "/lc/posteriors"}
    assert _remaps(options, "pose_graph_node") == {
        "odom": "/odometry/filtered", "loop_closures": "/slam/loop_closures", "place_posteriors": "/lc/posteriors"}
    assert _parameters(options, "verifier_node") == {"depth_topic": "/camera/depth_registered/image_raw",
                                                     "sensor_qos": "best_effort"}
    assert _parameters(options, "pose_graph_node") == {"sensor_qos": "best_effort"}
    explicit = SuiteOptions(model_dir="/m", image_topic="/camera/rgb/image_raw", camera_info_topic="/calib/info")
    assert _remaps(explicit, "verifier_node") == {"camera_info": "/calib/info"}
    unverified = SuiteOptions(model_dir="/m", verify=False, closures_topic="/slam/loop_closures")
    assert _remaps(unverified, "fabmap_node") == {"loop_closure_candidates": "/slam/loop_closures"}


def test_a_remap_without_its_two_sides_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match="remap 'odom' must be FROM:=TO"):
        suite_nodes(SuiteOptions(model_dir="/m", remaps=("odom",)))


def test_pictures_add_the_view_node_on_the_robots_image_and_closures_topics() -> None:
    nodes = suite_nodes(SuiteOptions(model_dir="m", image_topic="/cam/image_raw", closures_topic="/lc/closures",
                                     pictures=True))
    view = nodes[-1]
    assert view.name == "closure_view_node"
    assert view.remaps == {"image": "/cam/image_raw", "loop_closures": "/lc/closures"}
    assert "closure_view_node" not in [node.name for node in suite_nodes(SuiteOptions(model_dir="m"))]


def test_a_map_keeps_the_backend_s_graph_beside_it_and_the_robot_names_its_sessions() -> None:
    options = SuiteOptions(model_dir="/m", map_file="/maps/office.npz", backend=True, robot="r1")
    assert _parameters(options, "fabmap_node") == {"model_dir": "/m", "map_file": "/maps/office.npz", "robot": "r1"}
    backend = _parameters(options, "pose_graph_node")
    assert backend == {"graph_file": "/maps/office.graph.npz", "robot": "r1"}
    assert _parameters(options, "verifier_node")["store_dir"] == "/maps/office.features"


def test_without_a_map_the_backend_keeps_its_graph_in_memory() -> None:
    options = SuiteOptions(model_dir="/m", backend=True)
    assert "graph_file" not in _parameters(options, "pose_graph_node")
    assert "robot" not in _parameters(options, "fabmap_node")


def test_the_base_stations_backend_takes_every_robots_odometry() -> None:
    """--base --robots A,B --backend: pose_graph_node gets the robots (each one's /<robot>/aefabmap/odom), the first
    of them as its own robot (its first session anchors the map), and the graph file beside the map; a single host's
    backend gets no robots."""
    base = _parameters(SuiteOptions(model_dir="/m", base=True, robots=("robot1", "robot2"), backend=True,
                                    map_file="/maps/o.npz"), "pose_graph_node")
    assert base == {"graph_file": "/maps/o.graph.npz", "robot": "robot1", "robots": "[robot1,robot2]"}
    assert "robots" not in _parameters(SuiteOptions(model_dir="/m", backend=True), "pose_graph_node")
