"""The suite's nodes with their parameters and remaps: one table for both ways of starting them.

``aefabmap_launch`` (pip installs: OS processes) and ``launch/aefabmap.launch.py`` (``ros2 launch``)
both call :func:`suite_nodes` and only render its answer, as command lines or as launch_ros
``Node`` actions, so the two cannot drift apart. No ROS imports here.

Verification is on by default: fabmap_node publishes FAB-MAP's raw closures on
``loop_closure_candidates`` and verifier_node publishes the geometrically verified ones on
``loop_closures``, the topic a SLAM backend subscribes to. With verification off there is no
verifier and fabmap_node's ``loop_closure_candidates`` is remapped to ``loop_closures``, so the
backend's subscription stays the same (``inliers`` -1 there says "not verified").
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

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


@dataclass(frozen=True)
class NodeLaunch:
    """One node: its name (also its executable and ``aefabmap_ros.nodes.<name>`` module), the
    parameters set after the parameter file, and its topic remaps."""

    name: str
    parameters: dict[str, str] = field(default_factory=dict)
    remaps: dict[str, str] = field(default_factory=dict)

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


def suite_nodes(options: SuiteOptions) -> list[NodeLaunch]:
    """The nodes to start, in start order, with what each gets beyond the parameter file."""
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
