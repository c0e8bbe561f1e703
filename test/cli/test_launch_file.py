"""launch/aefabmap.launch.py starts the same nodes, parameters and remaps as aefabmap_launch.

There is no launch / launch_ros wheel, so the launch file is run here against small stand-ins of
the classes it uses (same constructor signatures as launch and launch_ros in Jazzy); where the
real packages are importable, a second test builds the description with them.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from typing import Any

import pytest

from aefabmap_ros.cli import launch
from aefabmap_ros.nodes.launch_table import CANDIDATES_TOPIC, CLOSURES_TOPIC
from test.conftest import REPO_ROOT

LAUNCH_FILE = REPO_ROOT / "launch" / "aefabmap.launch.py"
TOPIC_ARGUMENTS = ("camera_info_topic", "depth_topic", "odom_topic", "closures_topic", "sensor_qos", "robot")
FLEET_ARGUMENTS = {"robot_side": "false", "base": "false", "robots": ""}  # several robots: docs/fleet.md
SHIPPED_PARAMS = str(REPO_ROOT / "aefabmap_ros" / "config" / "aefabmap.yaml")
SHARE_PARAMS = "/opt/share/aefabmap_ros/config/aefabmap.yaml"  # what the stand-in FindPackageShare resolves to


class _Context:
    def __init__(self, configurations: dict[str, str]) -> None:
        self.launch_configurations = configurations


class _LaunchDescription:
    def __init__(self, initial_entities: list[Any] | None = None) -> None:
        self.entities = list(initial_entities or [])


class _DeclareLaunchArgument:
    def __init__(self, name: str, *, default_value: Any = None, description: str | None = None,
                 choices: list[str] | None = None) -> None:
        self.name, self.default_value, self.description = name, default_value, description


class _OpaqueFunction:
    def __init__(self, *, function: Any, args: list[Any] | None = None, kwargs: dict[str, Any] | None = None) -> None:
        self.function, self.args, self.kwargs = function, args or [], kwargs or {}

    def execute(self, context: _Context) -> list[Any]:
        return list(self.function(context, *self.args, **self.kwargs) or [])


class _LaunchConfiguration:
    def __init__(self, variable_name: str, *, default: Any = None) -> None:
        self.variable_name = variable_name

    def perform(self, context: _Context) -> str:
        return context.launch_configurations[self.variable_name]


class _FindPackageShare:
    def __init__(self, package: str) -> None:
        self.package = package


class _PathJoinSubstitution:
    def __init__(self, substitutions: list[Any]) -> None:
        self.substitutions = substitutions

    def perform(self, _context: _Context) -> str:
        parts = [f"/opt/share/{s.package}" if isinstance(s, _FindPackageShare) else s for s in self.substitutions]
        return "/".join(parts)


class _Node:
    def __init__(self, *, executable: str, package: str | None = None, name: str | None = None,
                 namespace: str | None = None, exec_name: str | None = None, parameters: list[Any] | None = None,
                 remappings: list[tuple[str, str]] | None = None, ros_arguments: list[str] | None = None,
                 arguments: list[str] | None = None, **kwargs: Any) -> None:
        self.package, self.executable, self.name, self.namespace = package, executable, name, namespace
        self.parameters, self.remappings, self.kwargs = parameters or [], remappings or [], kwargs


def _stand_in_modules() -> dict[str, types.ModuleType]:
    def module(name: str, **members: Any) -> types.ModuleType:
        made = types.ModuleType(name)
        made.__dict__.update(members)
        return made

    return {
        "launch": module("launch", LaunchDescription=_LaunchDescription),
        "launch.actions": module("launch.actions", DeclareLaunchArgument=_DeclareLaunchArgument,
                                 OpaqueFunction=_OpaqueFunction),
        "launch.substitutions": module("launch.substitutions", LaunchConfiguration=_LaunchConfiguration,
                                       PathJoinSubstitution=_PathJoinSubstitution),
        "launch_ros": module("launch_ros"),
        "launch_ros.actions": module("launch_ros.actions", Node=_Node),
        "launch_ros.substitutions": module("launch_ros.substitutions", FindPackageShare=_FindPackageShare),
    }


def _load_launch_file() -> Any:
    spec = importlib.util.spec_from_file_location("aefabmap_launch_file", LAUNCH_FILE)
    assert spec is not None and spec.loader is not None
    loaded = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(loaded)
    return loaded


@pytest.fixture
def launch_file(monkeypatch: pytest.MonkeyPatch) -> Any:
    for name, stand_in in _stand_in_modules().items():
        monkeypatch.setitem(sys.modules, name, stand_in)
    return _load_launch_file()


Started = list[tuple[str, str, dict[str, str], dict[str, str]]]  # (node, parameter file, -p values, remaps)


def _ros2_launch(launch_file: Any, arguments: dict[str, str]) -> Started:
    """What `ros2 launch aefabmap_ros aefabmap.launch.py key:=value ...` would start."""
    description = launch_file.generate_launch_description()
    declared = [e for e in description.entities if isinstance(e, _DeclareLaunchArgument)]
    configurations = {}
    for argument in declared:
        if argument.name in arguments:
            configurations[argument.name] = arguments[argument.name]
        else:
            default = argument.default_value
            assert default is not None, f"launch argument {argument.name} is required"
            configurations[argument.name] = default if isinstance(default, str) else default.perform(None)
    assert set(arguments) <= set(configurations), "unknown launch argument"
    context = _Context(configurations)
    started: Started = []
    for entity in description.entities:
        if isinstance(entity, _OpaqueFunction):
            for node in entity.execute(context):
                assert isinstance(node, _Node) and node.package == "aefabmap_ros" and node.executable == node.name
                params_file, overrides = node.parameters
                namespace = {"__ns": node.namespace} if node.namespace else {}
                started.append((node.name, _sections(params_file, node.namespace), dict(overrides),
                                {**dict(node.remappings), **namespace}))
    return started


def _sections(params_file: str, namespace: str | None) -> str:
    """A namespaced node's parameter file is a renamed copy: compared by its sections' names and values."""
    if not namespace:
        return params_file
    import yaml

    with open(params_file) as source:
        content = yaml.safe_load(source)
    return repr(sorted((name, repr(section)) for name, section in content.items()))


def _aefabmap_launch(argv: list[str]) -> Started:
    """What `aefabmap_launch argv...` would start, parsed back from its command lines."""
    started: Started = []
    for command in launch.node_commands(launch.build_parser().parse_args(argv)):
        assert command[1] == "-m" and command[2].startswith("aefabmap_ros.nodes.")
        ros_args = command[4:]
        assert command[3] == "--ros-args" and ros_args[0] == "--params-file"
        pairs = list(zip(ros_args[2::2], ros_args[3::2], strict=True))
        parameters = dict(value.split(":=", 1) for flag, value in pairs if flag == "-p")
        remaps = dict(value.split(":=", 1) for flag, value in pairs if flag == "-r")
        assert all(flag in ("-p", "-r") for flag, _ in pairs)
        namespace = remaps.get("__ns")
        started.append((command[2].removeprefix("aefabmap_ros.nodes."), _sections(ros_args[1], namespace),
                         parameters, remaps))
    return started


CASES = [  # (ros2 launch arguments, the same choice for aefabmap_launch)
    ({"model_dir": "/m"}, ["--model", "/m"]),
    ({"model_dir": "/m", "verify": "false"}, ["--model", "/m", "--no-verify"]),
    ({"model_dir": "/m", "verify": "False"}, ["--model", "/m", "--no-verify"]),
    ({"model_dir": "/m", "verify": "true", "map_file": "/maps/office.npz", "image_topic": "/cam/image_raw",
      "image_qos": "reliable", "params_file": "/p.yaml"},
     ["--model", "/m", "--verify", "--map", "/maps/office.npz", "--image-topic", "/cam/image_raw",
      "--image-qos", "reliable", "--params", "/p.yaml"]),
    ({"model_dir": "/m", "verify": "0", "map_file": "/maps/office.npz"},
     ["--model", "/m", "--no-verify", "--map", "/maps/office.npz"]),
    ({"model_dir": "/m", "backend": "true"}, ["--model", "/m", "--backend"]),
    ({"model_dir": "/m", "pictures": "true"}, ["--model", "/m", "--pictures"]),
    ({"model_dir": "/m", "backend": "true", "image_topic": "/camera/rgb/image_raw",
      "camera_info_topic": "/camera/rgb/info", "depth_topic": "/camera/depth_registered/image_raw",
      "odom_topic": "/odometry/filtered", "closures_topic": "/slam/loops", "sensor_qos": "best_effort"},
     ["--model", "/m", "--backend", "--image-topic", "/camera/rgb/image_raw", "--camera-info-topic",
      "/camera/rgb/info", "--depth-topic", "/camera/depth_registered/image_raw", "--odom-topic",
      "/odometry/filtered", "--closures-topic", "/slam/loops", "--sensor-qos", "best_effort"]),
    ({"model_dir": "/m", "robot_side": "true", "robot": "robot1", "depth_topic": "depth",
      "params_file": SHIPPED_PARAMS},
     ["--model", "/m", "--robot-side", "--robot", "robot1", "--depth-topic", "depth", "--params", SHIPPED_PARAMS]),
    ({"model_dir": "/m", "base": "true", "robots": "robot1,robot2", "backend": "true", "map_file": "/maps/o.npz"},
     ["--model", "/m", "--base", "--robots", "robot1,robot2", "--backend", "--map", "/maps/o.npz"]),
]


@pytest.mark.parametrize(("arguments", "argv"), CASES)
def test_launch_file_starts_what_aefabmap_launch_starts(launch_file: Any, arguments: dict[str, str],
                                                         argv: list[str]) -> None:
    from_launch_file = _ros2_launch(launch_file, arguments)
    if "params_file" not in arguments:  # the installed share folder vs. the source tree's config/
        assert all(params == SHARE_PARAMS for _, params, _, _ in from_launch_file)
        argv = [*argv, "--params", SHARE_PARAMS]
    assert from_launch_file == _aefabmap_launch(argv)


def test_verification_is_on_by_default_and_one_switch_turns_it_off(launch_file: Any) -> None:
    verified = _ros2_launch(launch_file, {"model_dir": "/m"})
    assert [name for name, *_ in verified] == ["feature_node", "quantizer_node", "fabmap_node", "verifier_node"]
    assert all(remaps.get(CANDIDATES_TOPIC) is None for *_, remaps in verified)  # fabmap_node -> verifier_node
    raw = _ros2_launch(launch_file, {"model_dir": "/m", "verify": "false"})
    assert [name for name, *_ in raw] == ["feature_node", "quantizer_node", "fabmap_node"]
    assert raw[2][3] == {CANDIDATES_TOPIC: CLOSURES_TOPIC}  # the backend's subscription does not change
    with pytest.raises(Exception, match="verify='maybe' must be true or false"):
        _ros2_launch(launch_file, {"model_dir": "/m", "verify": "maybe"})


def test_backend_adds_the_pose_graph_node(launch_file: Any) -> None:
    with_backend = _ros2_launch(launch_file, {"model_dir": "/m", "backend": "true"})
    assert [name for name, *_ in with_backend] == ["feature_node", "quantizer_node", "fabmap_node", "verifier_node",
                                                   "pose_graph_node"]


def test_launch_file_with_the_real_launch_packages() -> None:
    """Only where launch and launch_ros are installed (a full ROS 2 Jazzy install)."""
    pytest.importorskip("launch_ros")  # first: from the repository root, `launch` alone finds the launch/ folder
    actions = importlib.import_module("launch.actions")
    real_launch = importlib.import_module("launch")
    utilities = importlib.import_module("launch.utilities")
    description = _load_launch_file().generate_launch_description()
    arguments = {a.name: a for a in description.entities if isinstance(a, actions.DeclareLaunchArgument)}
    assert set(arguments) == {"model_dir", "params_file", "map_file", "image_topic", "image_qos", "verify",
                              "backend", "pictures", *TOPIC_ARGUMENTS, *FLEET_ARGUMENTS}
    context = real_launch.LaunchContext()
    assert utilities.perform_substitutions(context, arguments["verify"].default_value) == "true"
    (opaque,) = [e for e in description.entities if isinstance(e, actions.OpaqueFunction)]
    context.launch_configurations.update({"model_dir": "/m", "params_file": "/p.yaml", "map_file": "",
                                          "image_topic": "image", "image_qos": "", "verify": "true",
                                          "backend": "false", "pictures": "false",
                                          **dict.fromkeys(TOPIC_ARGUMENTS, ""), **FLEET_ARGUMENTS})
    assert len(opaque.execute(context)) == 4
    context.launch_configurations["verify"] = "false"
    assert len(opaque.execute(context)) == 3


def test_launch_file_gives_every_node_its_share_of_the_thread_pools(launch_file: Any,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    from aefabmap_ros.nodes.launch_table import THREAD_LIMIT_VARIABLES, threads_per_process

    for name in THREAD_LIMIT_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("NUMBA_NUM_THREADS", "3")  # the user's own choice stays theirs
    description = launch_file.generate_launch_description()
    (opaque,) = [e for e in description.entities if isinstance(e, _OpaqueFunction)]
    context = _Context({"model_dir": "/m", "params_file": "/p.yaml", "map_file": "", "image_topic": "image",
                        "image_qos": "", "verify": "true", "backend": "false", "pictures": "false",
                        **dict.fromkeys(TOPIC_ARGUMENTS, ""), **FLEET_ARGUMENTS})
    nodes = opaque.execute(context)
    share = str(threads_per_process(len(nodes)))
    for node in nodes:
        assert node.kwargs["additional_env"] == {"OMP_NUM_THREADS": share, "OPENBLAS_NUM_THREADS": share,
                                                 "MKL_NUM_THREADS": share}
