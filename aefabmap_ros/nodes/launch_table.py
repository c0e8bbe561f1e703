"""The suite's nodes with their parameters and remaps: one table for both ways of starting them.

``aefabmap_launch`` (pip installs: OS processes) and ``launch/aefabmap.launch.py`` (``ros2 launch``)
both call :func:`suite_nodes` and only render its answer, as command lines or as launch_ros
``Node`` actions, so the two cannot drift apart. No ROS imports here.

Verification is on by default: fabmap_node publishes FAB-MAP's raw closures on
``loop_closure_candidates`` and verifier_node publishes the geometrically verified ones on
``loop_closures``, the topic a SLAM backend subscribes to. With verification off there is no
verifier and fabmap_node's ``loop_closure_candidates`` is remapped to ``loop_closures``, so the
backend's subscription stays the same (``inliers`` -1 there says "not verified").

Several robots and a base station (docs/fleet.md): ``robot_side`` starts a robot's front end in the namespace
``/<robot>`` -- feature_node, quantizer_node (its words onto ``aefabmap/robot_words``) and feature_server_node,
which sends the base the words of every frame and the features of the frames it asks for; ``base`` starts the
base station's fabmap_node (one map, ``robots``), verifier_node (the robots' frames on request) and, with
``backend``, pose_graph_node (every robot's odometry, ``robots``). Neither flag: the single host, as always.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from aefabmap_ros.errors import ConfigError

PACKAGE = "aefabmap_ros"
CANDIDATES_TOPIC = "loop_closure_candidates"  # fabmap_node's raw FAB-MAP closures
CLOSURES_TOPIC = "loop_closures"  # what a SLAM backend subscribes to
POSTERIORS_TOPIC = "place_posteriors"
CLOSURE_PICTURES_TOPIC = "closure_view/closures"  # closure_view_node: each closure with its matches drawn
REFUSED_PICTURES_TOPIC = "closure_view/refused"  # closure_view_node: FAB-MAP's candidates the verifier refused
# feature_node: each frame that got features with a small JPEG of it, only while subscribed (closure_view_node).
FRAME_VIEWS_TOPIC = "aefabmap/frame_views"
GRAPH_MARKERS_TOPIC = "pose_graph/markers"  # pose_graph_node: the graph as visualization_msgs/MarkerArray
# What the live view (aefabmap_view) serves and a viewable recording holds, with the topics' types.
VIEW_TOPICS = {
    CLOSURE_PICTURES_TOPIC: "sensor_msgs/msg/CompressedImage",
    REFUSED_PICTURES_TOPIC: "sensor_msgs/msg/CompressedImage",
    GRAPH_MARKERS_TOPIC: "visualization_msgs/msg/MarkerArray",
    "pose_graph/path": "nav_msgs/msg/Path",
    CLOSURES_TOPIC: "aefabmap_msgs/msg/LoopClosure",
    CANDIDATES_TOPIC: "aefabmap_msgs/msg/LoopClosure",
    POSTERIORS_TOPIC: "aefabmap_msgs/msg/PlacePosterior",
}
DETECTION_NODES = ("feature_node", "quantizer_node", "fabmap_node")  # aefabmap_pipeline runs these three
FEATURE_SERVER_NODE = "feature_server_node"
ROBOT_NODES = ("feature_node", "quantizer_node", FEATURE_SERVER_NODE)  # aefabmap_robot_pipeline runs these three
# On a robot, quantizer_node's words go to the feature server, which sends them on aefabmap/words without
# keypoint_words. The rule names its node, so in one process (robot_pipeline) it moves quantizer_node's only.
ROBOT_WORDS_REMAP = ("quantizer_node:aefabmap/words", "aefabmap/robot_words")
VERIFIER_NODE = "verifier_node"
BACKEND_NODE = "pose_graph_node"
VIEW_NODE = "closure_view_node"
# Thread pools that OpenMP (torch), OpenBLAS/MKL (numpy, scipy) and numba each size to the machine's
# cores by default: with several node processes that is cores x processes x pools threads fighting
# for the same cores, so the launchers give each process its share unless the user chose a value.
THREAD_LIMIT_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


@dataclass(frozen=True)
class SuiteOptions:
    """What a user chooses when starting the suite (command-line options / launch arguments).

    Topic options name the robot's own topics; '' keeps the default: camera_info beside the image topic
    (image_transport's convention), the parameter file's depth_topic, ``odom``, ``loop_closures``.
    """

    model_dir: str
    map_file: str = ""  # '' = the map stays in memory
    robot: str = ""  # the robot's name, kept with each session of the map and the backend's graph
    image_topic: str = "image"
    image_qos: str = ""  # '' = the parameter file's value
    verify: bool = True
    backend: bool = False  # also start pose_graph_node, the example SLAM backend (odometry on ``odom``)
    pictures: bool = False  # also start closure_view_node (closure pictures, drawn only while subscribed)
    camera_info_topic: str = ""
    depth_topic: str = ""
    odom_topic: str = ""
    closures_topic: str = ""
    sensor_qos: str = ""  # verifier's and backend's camera_info/depth/odom QoS; '' = the parameter file's value
    remaps: tuple[str, ...] = ()  # further FROM:=TO remaps, given to every node
    robot_side: bool = False  # a robot's front end for a base station, in namespace /<robot> (docs/fleet.md)
    base: bool = False  # a base station for ``robots``
    robots: tuple[str, ...] = ()  # the base station's robots


@dataclass(frozen=True)
class NodeLaunch:
    """One node: its name (also its executable and ``aefabmap_ros.nodes.<name>`` module), the
    parameters set after the parameter file, its topic remaps and its namespace ('' = the launcher's)."""

    name: str
    parameters: dict[str, str] = field(default_factory=dict)
    remaps: dict[str, str] = field(default_factory=dict)
    namespace: str = ""

    @property
    def module(self) -> str:
        return f"{PACKAGE}.nodes.{self.name}"


def verifier_store_path(map_path: Path) -> Path:
    """Where verifier_node keeps its feature store beside a FAB-MAP map: office.npz -> office.features/."""
    return map_path.with_suffix(".features")


def backend_graph_path(map_path: Path) -> Path:
    """Where pose_graph_node keeps its pose graph beside a FAB-MAP map: office.npz -> office.graph.npz. Kept with
    the map, so a session that closes a loop into an earlier one finds that session's keyframes and odometry."""
    return map_path.with_suffix(".graph.npz")


def parse_bool(value: str, what: str) -> bool:
    """A launch argument's truth value, as launch's IfCondition reads it (true/false/1/0, any case)."""
    lowered = value.strip().lower()
    if lowered in ("true", "1"):
        return True
    if lowered in ("false", "0"):
        return False
    raise ConfigError(f"{what}={value!r} must be true or false")


def camera_info_beside(image_topic: str) -> str:
    """image_transport's camera_info topic of an image topic: ``/cam/rgb/image_raw`` -> ``/cam/rgb/camera_info``."""
    namespace, _, _name = image_topic.rstrip("/").rpartition("/")
    if not namespace:
        return "/camera_info" if image_topic.startswith("/") else "camera_info"
    return f"{namespace}/camera_info"


def parse_remaps(remaps: tuple[str, ...]) -> dict[str, str]:
    """``FROM:=TO`` strings -> {FROM: TO}; a ConfigError names one without ``:=`` or with an empty side."""
    parsed = {}
    for remap in remaps:
        source, separator, target = remap.partition(":=")
        if not separator or not source.strip() or not target.strip():
            raise ConfigError(f"remap {remap!r} must be FROM:=TO (e.g. odom:=/odometry/filtered)")
        parsed[source.strip()] = target.strip()
    return parsed


# A robot name is one token of a ROS namespace: its topics live under /<robot>/.
ROBOT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


def parse_robots(value: Any, what: str) -> list[str]:
    """The robot names of a parameter or option value ([] for none); ConfigError for a bad or repeated name."""
    if value is None or value == "" or (isinstance(value, list | tuple) and not value):
        return []
    # A string: "robot1,robot2", or "[robot1,robot2]" as a launch file passes the parameter through.
    names = [name.strip() for name in value.strip().strip("[]").split(",")] if isinstance(value, str) \
        else list(value)
    bad = [name for name in names if not isinstance(name, str) or not ROBOT_NAME.fullmatch(name)]
    if bad:
        raise ConfigError(f"{what}: robot names must be namespace tokens (a letter, then letters, digits or _), "
                          f"got {bad}")
    if len(set(names)) != len(names):
        raise ConfigError(f"{what}: a robot is named twice in {names}")
    return names


def robot_namespace(robot: str) -> str:
    """The namespace of a robot's nodes and topics: ``robot1`` -> ``/robot1``."""
    return f"/{robot}"


def namespaced_sections(content: Mapping[str, Any], namespace: str) -> dict[str, Any]:
    """A parameter file's sections for nodes started in ``namespace``: rcl gives a section to the node whose full
    name it is, so ``feature_node`` becomes ``/robot1/feature_node`` (keys from ``/``, e.g. ``/**``, stay)."""
    return {(key if key.startswith("/") else f"{namespace}/{key}"): section for key, section in content.items()}


def robots_parameter(robots: tuple[str, ...]) -> str:
    """The ``robots`` parameter as a command-line value: ``[robot1,robot2]``."""
    return f"[{','.join(robots)}]"


def check_fleet_options(options: SuiteOptions) -> None:
    """A ConfigError for a robot side or base without its robots, or both at once."""
    if options.robot_side and options.base:
        raise ConfigError("--robot-side and --base start the two ends of the link: one of them per host")
    if options.robot_side and not options.robot:
        raise ConfigError("--robot-side needs --robot NAME: its nodes and topics live in namespace /NAME")
    if options.robot_side and (options.map_file or options.backend):
        raise ConfigError("--robot-side runs the robot's front end only; the map and the backend are the base "
                          "station's (--base)")
    if (options.robot_side or options.base) and options.pictures:
        raise ConfigError("--pictures draws on the camera's frames, which stay on the robots: not with "
                          "--robot-side or --base")
    if options.base and not options.robots:
        raise ConfigError("--base needs --robots NAME,NAME,...: the robots whose words and features it takes")
    if options.robots and not options.base:
        raise ConfigError("--robots names a base station's robots: give --base too")


def robot_side_nodes(options: SuiteOptions) -> list[NodeLaunch]:
    """A robot's front end for a base station, in its namespace: features, words, and the feature server."""
    image: dict[str, str] = {"image_qos": options.image_qos} if options.image_qos else {}
    busy: dict[str, str] = (
        {"drop_when_busy": str(options.image_qos not in ("reliable",)).lower()} if options.image_qos else {}
    )
    extra = parse_remaps(options.remaps)
    namespace = robot_namespace(options.robot)
    camera_info = options.camera_info_topic or camera_info_beside(options.image_topic)
    beside = {"camera_info": camera_info} if camera_info != "camera_info" else {}
    depth = {"depth_topic": options.depth_topic} if options.depth_topic else {}
    sensors: dict[str, str] = {"sensor_qos": options.sensor_qos} if options.sensor_qos else {}
    odometry = {"odom": options.odom_topic} if options.odom_topic else {}
    return [
        NodeLaunch("feature_node", {"model_dir": options.model_dir, **image, **busy},
                   {"image": options.image_topic, **extra}, namespace),
        NodeLaunch("quantizer_node", {"model_dir": options.model_dir, **busy}, {**extra, ROBOT_WORDS_REMAP[0]:
                                                                                ROBOT_WORDS_REMAP[1]}, namespace),
        NodeLaunch(FEATURE_SERVER_NODE, {"robot": options.robot, **depth, **sensors},
                   {**extra, **beside, **odometry}, namespace),
    ]


def base_nodes(options: SuiteOptions) -> list[NodeLaunch]:
    """A base station's nodes: one map for every robot, the verifier asking the robots for features, a backend."""
    extra = parse_remaps(options.remaps)
    robots = {"robots": robots_parameter(options.robots)}
    fabmap: dict[str, str] = {"map_file": options.map_file} if options.map_file else {}
    closures = options.closures_topic or CLOSURES_TOPIC
    published = {CLOSURES_TOPIC: closures} if closures != CLOSURES_TOPIC else {}
    sensors: dict[str, str] = {"sensor_qos": options.sensor_qos} if options.sensor_qos else {}
    nodes = [NodeLaunch("fabmap_node", {"model_dir": options.model_dir, **fabmap, **robots},
                        {**extra, **({} if options.verify else {CANDIDATES_TOPIC: closures})})]
    if options.verify:
        store = {"store_dir": str(verifier_store_path(Path(options.map_file)))} if options.map_file else {}
        nodes.append(NodeLaunch(VERIFIER_NODE, {**store, **sensors, **robots}, {**extra, **published}))
    if options.backend:  # every robot's odometry, /<robot>/aefabmap/odom; the first robot's holds the map frame
        graph = {"graph_file": str(backend_graph_path(Path(options.map_file)))} if options.map_file else {}
        nodes.append(NodeLaunch(BACKEND_NODE, {**sensors, **graph, "robot": options.robots[0], **robots},
                                {**extra, **published}))
    return nodes


def suite_nodes(options: SuiteOptions) -> list[NodeLaunch]:
    """The nodes to start, in start order, with what each gets beyond the parameter file."""
    check_fleet_options(options)
    if options.robot_side:
        return robot_side_nodes(options)
    if options.base:
        return base_nodes(options)
    image: dict[str, str] = {"image_qos": options.image_qos} if options.image_qos else {}
    # A live camera's frames may be dropped at every stage when busy, a lossless replay's at none.
    busy: dict[str, str] = (
        {"drop_when_busy": str(options.image_qos not in ("reliable",)).lower()} if options.image_qos else {}
    )
    sensors: dict[str, str] = {"sensor_qos": options.sensor_qos} if options.sensor_qos else {}
    fabmap: dict[str, str] = {"map_file": options.map_file} if options.map_file else {}
    robot: dict[str, str] = {"robot": options.robot} if options.robot else {}
    extra = parse_remaps(options.remaps)
    closures = options.closures_topic or CLOSURES_TOPIC
    odometry = {"odom": options.odom_topic} if options.odom_topic else {}
    published = {CLOSURES_TOPIC: closures} if closures != CLOSURES_TOPIC else {}
    nodes = [
        NodeLaunch("feature_node", {"model_dir": options.model_dir, **image, **busy},
                   {"image": options.image_topic, **extra}),
        NodeLaunch("quantizer_node", {"model_dir": options.model_dir, **busy}, dict(extra)),
        NodeLaunch("fabmap_node", {"model_dir": options.model_dir, **fabmap, **robot},
                   {**extra, **({} if options.verify else {CANDIDATES_TOPIC: closures})}),
    ]
    if options.verify:
        store = {"store_dir": str(verifier_store_path(Path(options.map_file)))} if options.map_file else {}
        depth = {"depth_topic": options.depth_topic} if options.depth_topic else {}
        camera_info = options.camera_info_topic or camera_info_beside(options.image_topic)
        beside = {"camera_info": camera_info} if camera_info != "camera_info" else {}
        nodes.append(NodeLaunch(VERIFIER_NODE, {**store, **depth, **sensors},
                                {**extra, **beside, **odometry, **published}))
    if options.backend:
        graph = {"graph_file": str(backend_graph_path(Path(options.map_file)))} if options.map_file else {}
        nodes.append(NodeLaunch(BACKEND_NODE, {**sensors, **graph, **robot}, {**extra, **odometry, **published}))
    if options.pictures:
        nodes.append(NodeLaunch(VIEW_NODE, {}, {"image": options.image_topic, **extra, **published}))
    return nodes


def params_file_problem(path: Path) -> str | None:
    """Why rcl would refuse this parameter file, found before any node starts (each node would otherwise
    print its own traceback), or None. rcl wants ``<node name>: {ros__parameters: {...}}`` at the top."""
    import yaml

    try:
        content = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        return f"--params {path}: cannot read it: {exc}"
    except yaml.YAMLError as exc:
        return f"--params {path} is not valid YAML: {' '.join(str(exc).split())}"
    if not isinstance(content, dict):
        return f"--params {path} must map node names to their parameters, got {type(content).__name__}"
    for node_name, section in content.items():
        if not _is_parameter_section(section):
            return f"--params {path}: section {node_name!r} must hold a 'ros__parameters:' mapping"
    return None


def _is_parameter_section(section: object) -> bool:
    """``{ros__parameters: {...}}``, or a namespace level (``/ns: {node: {ros__parameters: ...}}``)."""
    if not isinstance(section, dict) or not section:
        return False
    if "ros__parameters" in section:
        return isinstance(section["ros__parameters"], dict)
    return all(_is_parameter_section(inner) for inner in section.values())


def compressed_topic(image_topic: str) -> str:
    """image_transport's compressed topic of an image topic: ``/cam/image`` -> ``/cam/image/compressed``."""
    return f"{image_topic.rstrip('/')}/compressed"


def threads_per_process(processes: int, cores: int | None = None) -> int:
    """Each process's share of the cores (at least 1): the node processes then start no more
    pool threads together than the machine has cores (rounding down, but never to zero)."""
    available = cores if cores is not None else (os.cpu_count() or 1)
    return max(1, available // max(1, processes))


def thread_limits(processes: int, environment: Mapping[str, str], cores: int | None = None) -> dict[str, str]:
    """The thread-pool variables to add to each node process's environment: its share of the cores
    for every variable of ``THREAD_LIMIT_VARIABLES`` the user has not set (theirs win)."""
    share = str(threads_per_process(processes, cores))
    return {name: share for name in THREAD_LIMIT_VARIABLES if not environment.get(name)}
