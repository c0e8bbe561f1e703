"""aefabmap_launch --view: the closure pictures' node and the Foxglove server beside the suite's nodes."""

from pathlib import Path

from aefabmap_ros.cli import launch


def _modules(tmp_path: Path, *options: str) -> list[str]:
    commands = launch.node_commands(launch.build_parser().parse_args(["--model", str(tmp_path), *options]))
    return [command[command.index("-m") + 1] for command in commands]


def test_view_starts_the_picture_node_and_the_server_on_its_port(tmp_path: Path) -> None:
    commands = launch.node_commands(launch.build_parser().parse_args(
        ["--model", str(tmp_path), "--view", "--view-port", "9001"]))
    assert commands[-1][-4:] == ["-m", "aefabmap_ros.cli.view", "--port", "9001"]
    assert "aefabmap_ros.nodes.closure_view_node" in _modules(tmp_path, "--view")
    assert "aefabmap_ros.nodes.closure_view_node" in _modules(tmp_path, "--view", "--pipeline")


def test_pictures_start_the_picture_node_without_a_server(tmp_path: Path) -> None:
    modules = _modules(tmp_path, "--pictures")
    assert "aefabmap_ros.nodes.closure_view_node" in modules and "aefabmap_ros.cli.view" not in modules
    assert not {"aefabmap_ros.nodes.closure_view_node", "aefabmap_ros.cli.view"} & set(_modules(tmp_path))
