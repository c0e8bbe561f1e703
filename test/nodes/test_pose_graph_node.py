"""pose_graph_node in this process, callbacks called directly: the square loop through ROS messages."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
msg = pytest.importorskip("aefabmap_msgs.msg")

from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from aefabmap_ros.nodes.gtsam_poses import gtsam_to_pose  # noqa: E402
from aefabmap_ros.nodes.messages import time_from_ns  # noqa: E402
from aefabmap_ros.nodes.pose_graph_node import PoseGraphNode  # noqa: E402
from test.backend.test_pose_graph import drifting_odometry, square_truth, stamp  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.usefixtures("ros_context")]


def _odometry(index: int, pose: Any) -> Odometry:
    message = Odometry()
    message.header.stamp = time_from_ns(stamp(index))
    message.pose.pose = gtsam_to_pose(pose)
    return message


def _captured_paths(node: PoseGraphNode) -> list[Any]:
    """The paths the node publishes, kept; its transforms dropped."""
    paths: list[Any] = []
    node.path_publisher.publish = paths.append
    node.tf_publisher.publish = lambda _message: None
    return paths


def _closure(query: int, place: int, relative: Any, with_pose: bool = True) -> Any:
    closure = msg.LoopClosure(query_id=query, matched_place_id=place)
    closure.header.stamp = time_from_ns(stamp(query))
    closure.matched_stamp = time_from_ns(stamp(place))
    closure.pose_available = with_pose
    closure.pose = gtsam_to_pose(relative)
    closure.pose_covariance = list(np.diag([0.02**2] * 3 + [0.005**2] * 3).reshape(36))
    closure.translation_metric = True
    return closure


def test_pose_graph_node_closes_the_loop_and_writes_tum(tmp_path: Path) -> None:
    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    output = tmp_path / "keyframes.tum"
    node = PoseGraphNode(parameter_overrides=[Parameter("trajectory_file", value=str(output))])
    try:
        paths: list[Any] = []
        transforms: list[Any] = []
        node.path_publisher.publish = paths.append
        node.tf_publisher.publish = transforms.append
        for index, pose in enumerate(odometry):
            node._on_odometry(_odometry(index, pose))
        node._on_odometry(_odometry(3, odometry[3]))  # out of order
        node._on_loop_closure(_closure(end, 0, truth[end].between(truth[0]), with_pose=False))  # no pose
        node._on_loop_closure(_closure(end, 0, truth[end].between(truth[0])))
        node._on_loop_closure(_closure(end, -5, truth[end].between(truth[0])))  # before the odometry
        assert not paths and len(transforms) == 1  # map -> odom at once; the path with the next period's changes
        node.publish_changes()
        node.publish_changes()  # nothing changed since: nothing more
        counts = node.counter.counts
        assert counts["added"] == 1
        assert counts["dropped_odometry_out_of_order"] == 1
        assert counts["dropped_no_pose"] == 1 and counts["dropped_unknown_stamp"] == 1
        (path,) = paths
        assert path.header.frame_id == "map" and len(path.poses) == 2
        last = path.poses[-1].pose.position
        end_error = np.linalg.norm(np.array([last.x, last.y, last.z]) - truth[end].translation())
        odometry_error = np.linalg.norm(odometry[end].translation() - truth[end].translation())
        assert end_error < 0.1 * odometry_error
        assert len(transforms) == 1
        node.close()
        lines = output.read_text().splitlines()
        assert len(lines) == 2 and float(lines[-1].split()[0]) == pytest.approx(stamp(end) / 1e9)
    finally:
        node.destroy_node()


def test_pose_graph_node_moves_camera_closures_to_the_base_frame() -> None:
    """A camera 0.5 m ahead of the base and turned 90 degrees: the camera-frame closure, conjugated by the
    ``base_to_camera`` parameter, closes the loop of the base's odometry as the base-frame closure does."""
    import gtsam

    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    base_to_camera = gtsam.Pose3(gtsam.Rot3.Yaw(np.pi / 2), np.array([0.5, 0.0, 0.2]))
    cameras = [pose.compose(base_to_camera) for pose in truth]
    qx, qy, qz, qw = 0.0, 0.0, float(np.sin(np.pi / 4)), float(np.cos(np.pi / 4))  # 90 degrees about z
    errors = {}
    for label, extrinsic in (("with", [0.5, 0.0, 0.2, qx, qy, qz, qw]), ("without", [0.0] * 6 + [1.0])):
        node = PoseGraphNode(parameter_overrides=[Parameter("base_to_camera", value=extrinsic)])
        try:
            paths = _captured_paths(node)
            for index, pose in enumerate(odometry):
                node._on_odometry(_odometry(index, pose))
            # To frame 2, not 0: the loop ends where it began, and an identity closure looks alike in any frame.
            node._on_loop_closure(_closure(end, 2, cameras[end].between(cameras[2])))
            node.publish_changes()
            last = paths[-1].poses[-1].pose.position if paths else None
            errors[label] = (np.inf if last is None else
                             float(np.linalg.norm(np.array([last.x, last.y, last.z]) - truth[end].translation())))
        finally:
            node.destroy_node()
    odometry_error = np.linalg.norm(odometry[end].translation() - truth[end].translation())
    assert errors["with"] < 0.1 * odometry_error
    assert errors["without"] > 0.5 * odometry_error  # the camera's closure taken as the base's: no help


def test_pose_graph_node_refuses_a_malformed_extrinsic() -> None:
    from aefabmap_ros.errors import ConfigError

    with pytest.raises(ConfigError, match="base_to_camera"):
        PoseGraphNode(parameter_overrides=[Parameter("base_to_camera", value=[0.0, 0.0, 0.0])])
    with pytest.raises(ConfigError, match="publish_period_s"):
        PoseGraphNode(parameter_overrides=[Parameter("publish_period_s", value=0.0)])


def test_pose_graph_node_publishes_map_to_odom_on_tf() -> None:
    """tf2_msgs is built into the venv (scripts/setup.sh): map -> odom goes out on /tf as a TFMessage."""
    from tf2_msgs.msg import TFMessage

    node = PoseGraphNode()
    try:
        assert node.tf_publisher.topic_name == "/tf" and node.tf_publisher.msg_type is TFMessage
        sent: list[Any] = []
        node.tf_publisher.publish = sent.append
        truth = square_truth()
        odometry = drifting_odometry(truth)
        for index, pose in enumerate(odometry):
            node._on_odometry(_odometry(index, pose))
        end = len(truth) - 1
        node._on_loop_closure(_closure(end, 0, truth[end].between(truth[0])))
        (message,) = sent
        (transform,) = message.transforms
        assert (transform.header.frame_id, transform.child_frame_id) == ("map", "odom")
    finally:
        node.destroy_node()


def _broken_odometry(index: int, pose: Any, field: str) -> Odometry:
    message = _odometry(index, pose)
    if field == "nan_w":
        message.pose.pose.orientation.w = float("nan")
    elif field == "zero_quaternion":
        message.pose.pose.orientation.x = message.pose.pose.orientation.y = 0.0
        message.pose.pose.orientation.z = message.pose.pose.orientation.w = 0.0
    elif field == "inf_position":
        message.pose.pose.position.x = float("inf")
    elif field == "nanosec":
        message.header.stamp.nanosec = 1_500_000_000
    return message


def test_pose_graph_node_counts_malformed_odometry_and_closures_and_goes_on(tmp_path: Path) -> None:
    """Each malformed kind is counted by its name and dropped; the valid odometry and closure that follow make
    the keyframes and the path as if the malformed ones had never come."""
    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    node = PoseGraphNode()
    try:
        paths = _captured_paths(node)
        for index, pose in enumerate(odometry):
            if index == 10:
                for field in ("nan_w", "zero_quaternion", "inf_position", "nanosec"):
                    node._on_odometry(_broken_odometry(index, pose, field))
            node._on_odometry(_odometry(index, pose))
        true_pose = truth[end].between(truth[0])
        broken: list[Any] = []
        for change in ("nan_pose", "zero_quaternion", "nan_covariance", "not_psd", "asymmetric"):
            closure = _closure(end, 0, true_pose)
            if change == "nan_pose":
                closure.pose.position.y = float("nan")
            elif change == "zero_quaternion":
                closure.pose.orientation.x = closure.pose.orientation.y = 0.0
                closure.pose.orientation.z = closure.pose.orientation.w = 0.0
            else:
                covariance = np.array(closure.pose_covariance).reshape(6, 6)
                if change == "nan_covariance":
                    covariance[3, 3] = float("nan")
                elif change == "not_psd":
                    covariance[0, 0] = -1.0
                else:
                    covariance[0, 5] = 0.5
                closure.pose_covariance = list(covariance.reshape(36))
            broken.append(closure)
        late = _closure(end, 0, true_pose)
        late.matched_stamp.nanosec = 2_000_000_000
        for closure in broken:
            node._on_loop_closure(closure)
        node._on_loop_closure(late)
        counts = node.counter.counts
        assert counts["dropped_bad_odometry"] == 4 and counts["dropped_bad_closure_pose"] == 5
        assert counts["dropped_bad_closure_stamp"] == 1
        node.publish_changes()
        assert node.graph.counts["odometry"] == len(odometry) and not paths and not node.graph.keyframes
        node._on_loop_closure(_closure(end, 0, true_pose))  # a valid one: the loop closes
        node.publish_changes()
        assert counts["added"] == 1 and len(paths) == 1 and len(paths[0].poses) == 2
        last = paths[0].poses[-1].pose.position
        assert np.linalg.norm(np.array([last.x, last.y, last.z]) - truth[end].translation()) < 0.1
        assert not any(key.startswith("dropped_") and key not in {"dropped_bad_odometry", "dropped_bad_closure_pose",
                                                                 "dropped_bad_closure_stamp"} for key in counts)
    finally:
        node.destroy_node()


def test_pose_graph_node_survives_any_exception_in_its_callbacks(monkeypatch: pytest.MonkeyPatch) -> None:
    """An exception the checks did not foresee is counted by its type and dropped (node_callback): the node lives."""
    truth = square_truth()
    odometry = drifting_odometry(truth)
    end = len(truth) - 1
    node = PoseGraphNode()
    try:
        paths = _captured_paths(node)
        for index, pose in enumerate(odometry):
            node._on_odometry(_odometry(index, pose))
        real = node.graph.add_closure

        def exploding(_closure: Any) -> Any:
            raise ValueError("a bug no check foresaw")

        monkeypatch.setattr(node.graph, "add_closure", exploding)
        node._on_loop_closure(_closure(end, 0, truth[end].between(truth[0])))
        assert node.counter.counts["dropped_ValueError"] == 1
        monkeypatch.setattr(node.graph, "add_closure", real)
        node._on_loop_closure(_closure(end, 0, truth[end].between(truth[0])))
        node.publish_changes()
        assert node.counter.counts["added"] == 1 and len(paths) == 1
    finally:
        node.destroy_node()


def test_pose_graph_node_reports_a_trajectory_it_cannot_write(tmp_path: Path) -> None:
    """close() is False (the process exits 1) when the trajectory file cannot be written; True when it can."""
    blocked = tmp_path / "not_a_folder"
    blocked.write_text("a file where the trajectory's folder should be")
    for path, written in ((blocked / "keyframes.tum", False), (tmp_path / "keyframes.tum", True)):
        node = PoseGraphNode(parameter_overrides=[Parameter("trajectory_file", value=str(path))])
        try:
            assert node.close() is written
            assert path.exists() is written
        finally:
            node.destroy_node()


def _session_closure(query_ns: int, place_ns: int, relative: Any, query_session: int, matched_session: int) -> Any:
    closure = msg.LoopClosure(query_session=query_session, matched_session=matched_session)
    closure.header.stamp = time_from_ns(query_ns)
    closure.matched_stamp = time_from_ns(place_ns)
    closure.pose_available = True
    closure.pose = gtsam_to_pose(relative)
    closure.pose_covariance = list(np.diag([0.02**2] * 3 + [0.005**2] * 3).reshape(36))
    closure.translation_metric = True
    return closure


def test_pose_graph_node_keeps_its_graph_across_runs(tmp_path: Path) -> None:
    """Run 1 (session 0) saves its graph on shutdown; run 2 reloads it, its odometry restarted at the identity
    (session 1): a closure into session 0 is added, B goes on the map, and the trajectory holds both runs."""
    from aefabmap_ros.backend.graph_file import load_graph
    from aefabmap_ros.backend.pose_graph import PoseGraphConfig
    from test.backend.test_sessions import b_odometry, b_offset, b_stamp, b_truth

    graph_file, trajectory_file = tmp_path / "office.graph.npz", tmp_path / "keyframes.tum"
    parameters = [Parameter("graph_file", value=str(graph_file)),
                  Parameter("trajectory_file", value=str(trajectory_file))]
    truth = square_truth()
    end = len(truth) - 1
    first = PoseGraphNode(parameter_overrides=parameters)
    try:
        _captured_paths(first)
        for index, pose in enumerate(truth):
            first._on_odometry(_odometry(index, pose))
        first._on_loop_closure(_closure(end, 0, truth[end].between(truth[0])))
        assert first.counter.counts["added"] == 1 and not graph_file.exists()  # saved at shutdown (or the period)
        assert first.close()
    finally:
        first.destroy_node()
    assert graph_file.exists() and len(trajectory_file.read_text().splitlines()) == 2

    second = PoseGraphNode(parameter_overrides=parameters)
    try:
        transforms: list[Any] = []
        _captured_paths(second)
        second.tf_publisher.publish = transforms.append
        assert list(second.graph.sessions) == [("", 0)]
        b_end = len(b_odometry()) - 1
        for index, pose in enumerate(b_odometry()):
            message = _odometry(0, pose)
            message.header.stamp = time_from_ns(b_stamp(index))
            second._on_odometry(message)
        b_truth_poses = b_truth()
        second._on_loop_closure(_session_closure(b_stamp(10), stamp(31), b_truth_poses[10].between(truth[31]), 1, 5))
        assert second.counter.counts["dropped_unknown_session"] == 1
        # B's own loop: added in B's own graph; its map -> odom is withheld until B is joined to the map.
        second._on_loop_closure(_session_closure(b_stamp(b_end), b_stamp(0),
                                                 b_truth_poses[b_end].between(b_truth_poses[0]), 1, 1))
        assert second.counter.counts["added"] == 1 and second.counter.counts["map_to_odom_unjoined"] == 1
        assert transforms == []
        second._on_loop_closure(_session_closure(b_stamp(10), stamp(31), b_truth_poses[10].between(truth[31]), 1, 0))
        assert second.counter.counts["added"] == 2
        assert not any(key.startswith("dropped_") and key != "dropped_unknown_session"
                       for key in second.counter.counts)
        (message,) = transforms
        (transform,) = message.transforms
        assert (transform.header.frame_id, transform.child_frame_id) == ("map", "odom")
        moved = transform.transform.translation
        assert np.allclose([moved.x, moved.y, moved.z], b_offset().translation(), atol=1e-3)
        assert second.close()
    finally:
        second.destroy_node()
    stamps_s = [float(line.split()[0]) for line in trajectory_file.read_text().splitlines()]
    expected_ns = [stamp(0), stamp(31), stamp(end), b_stamp(0), b_stamp(10), b_stamp(b_end)]
    assert stamps_s == pytest.approx([stamp_ns / 1e9 for stamp_ns in expected_ns])
    reloaded = load_graph(graph_file, PoseGraphConfig())
    assert list(reloaded.sessions) == [("", 0), ("", 1)] and reloaded.is_joined("", 1)


def test_pose_graph_node_writes_an_unjoined_session_beside_the_trajectory(tmp_path: Path) -> None:
    from test.backend.test_sessions import b_odometry, b_stamp, b_truth

    graph_file, trajectory_file = tmp_path / "office.graph.npz", tmp_path / "keyframes.tum"
    parameters = [Parameter("graph_file", value=str(graph_file)),
                  Parameter("trajectory_file", value=str(trajectory_file))]
    truth = square_truth()
    end = len(truth) - 1
    first = PoseGraphNode(parameter_overrides=parameters)
    try:
        _captured_paths(first)
        for index, pose in enumerate(truth):
            first._on_odometry(_odometry(index, pose))
        first._on_loop_closure(_closure(end, 0, truth[end].between(truth[0])))
        assert first.close()
    finally:
        first.destroy_node()
    second = PoseGraphNode(parameter_overrides=parameters)
    try:
        _captured_paths(second)
        for index, pose in enumerate(b_odometry()):
            message = _odometry(0, pose)
            message.header.stamp = time_from_ns(b_stamp(index))
            second._on_odometry(message)
        b_end = len(b_odometry()) - 1
        second._on_loop_closure(_session_closure(b_stamp(b_end), b_stamp(0), b_truth()[b_end].between(b_truth()[0]),
                                                 1, 1))
        assert second.close()
    finally:
        second.destroy_node()
    assert len(trajectory_file.read_text().splitlines()) == 2  # the map's: session 0 only
    beside = tmp_path / "keyframes.session1.tum"
    assert [float(line.split()[0]) for line in beside.read_text().splitlines()] == \
        pytest.approx([b_stamp(0) / 1e9, b_stamp(b_end) / 1e9])


@pytest.mark.parametrize("content", [b"not a graph at all", b""])
def test_pose_graph_node_refuses_a_broken_graph_file(tmp_path: Path, content: bytes) -> None:
    from aefabmap_ros.errors import ModelError

    broken = tmp_path / "office.graph.npz"
    broken.write_bytes(content)
    with pytest.raises(ModelError, match=str(broken)):
        PoseGraphNode(parameter_overrides=[Parameter("graph_file", value=str(broken))])
    assert broken.read_bytes() == content


def test_pose_graph_node_names_later_sessions_odometry_frames() -> None:
    from aefabmap_ros.errors import ConfigError
    from aefabmap_ros.nodes.graph_view import session_frame
    from aefabmap_ros.nodes.pose_graph_node import session_trajectory_path

    assert session_frame("odom_{robot}_{session}", ("rover", 2)) == "odom_rover_2"
    assert session_trajectory_path(Path("out/keyframes.tum"), ("rover", 3)) == Path("out/keyframes.rover.session3.tum")
    with pytest.raises(ConfigError, match="session_odom_frame"):
        PoseGraphNode(parameter_overrides=[Parameter("session_odom_frame", value="odom_{bad}")])


def test_a_posterior_of_a_new_session_moves_the_odometry_from_its_first_frame_on() -> None:
    """fabmap_node started a session while the backend ran (a relocated robot): the first posterior of that
    session tells the backend where its odometry begins, before any closure names it; another robot's
    posterior, an older session's and a dropped frame's (query_id -1) change nothing."""
    node = PoseGraphNode(parameter_overrides=[Parameter("robot", value="r1")])
    try:
        node.graph.start_session(("r1", 0))
        for index in range(6):
            node._on_odometry(_odometry(index, gtsam_pose_x(float(index))))

        def posterior(robot: str, session: int, index: int, query_id: int = 5) -> Any:
            message = msg.PlacePosterior(query_id=query_id, robot=robot, session=session)
            message.header.stamp = time_from_ns(stamp(index))
            return message

        node._on_posterior(posterior("r2", 3, 3))
        node._on_posterior(posterior("r1", 0, 3))
        node._on_posterior(posterior("r1", 1, 3, query_id=-1))
        assert node.graph.current == ("r1", 0)
        node._on_posterior(posterior("r1", 1, 4))
        assert node.graph.current == ("r1", 1)
        assert node.graph.sessions[("r1", 0)].odometry.samples()[0] == [stamp(i) for i in range(4)]
        assert node.graph.sessions[("r1", 1)].odometry.samples()[0] == [stamp(4), stamp(5)]
    finally:
        node.destroy_node()


def gtsam_pose_x(x: float) -> Any:
    import gtsam

    return gtsam.Pose3(gtsam.Rot3(), np.array([x, 0.0, 0.0]))


def _robot_closure(query: Any, query_index: int, place: Any, place_index: int) -> Any:
    """A LoopClosure of the true relative pose between two robots' frames (test/backend/test_robots.py)."""
    from test.backend.test_robots import closure

    true = closure(query, query_index, place, place_index)
    message = _session_closure(true.query_ns, true.place_ns, true.query_to_place, query[1], place[1])
    message.query_robot, message.matched_robot = query[0], place[0]
    return message


def test_pose_graph_node_takes_every_robots_odometry_and_puts_them_on_one_map(tmp_path: Path) -> None:
    """robots r1, r2: each one's odometry on its own topic (fed here through the callbacks, routed by robot), each
    one's session named by its posteriors; r2's own loop leaves r2 off the map (no map -> odom for it), the closure
    between the robots puts it on: r2/odom at r2's true offset, and the trajectory file holds both robots."""
    from test.backend.test_robots import END, R1, R2, r2_stamp
    from test.backend.test_sessions import b_odometry, b_offset

    trajectory_file = tmp_path / "keyframes.tum"
    node = PoseGraphNode(parameter_overrides=[Parameter("robots", value=["r1", "r2"]),
                                              Parameter("trajectory_file", value=str(trajectory_file))])
    try:
        assert [odometry.topic for odometry in node.odometry_inputs] == ["/r1/aefabmap/odom", "/r2/aefabmap/odom"]
        assert node.graph.robot == "r1"  # the first robot's first session anchors the map
        transforms: list[Any] = []
        _captured_paths(node)
        node.tf_publisher.publish = transforms.append
        for index, pose in enumerate(square_truth()):
            node._on_odometry(_odometry(index, pose), robot="r1")
            message = _odometry(index, b_odometry()[index])
            message.header.stamp = time_from_ns(r2_stamp(index))
            node._on_odometry(message, robot="r2")
        for robot, stamp_ns in (("r1", stamp(0)), ("r2", r2_stamp(0))):
            posterior = msg.PlacePosterior(query_id=0, robot=robot, session=0)
            posterior.header.stamp = time_from_ns(stamp_ns)
            node._on_posterior(posterior)
        assert node.graph.current_session("r1") == R1 and node.graph.current_session("r2") == R2
        assert len(node.graph.sessions[R2].odometry) == END + 1  # r2's odometry, kept until its session was named

        node._on_loop_closure(_robot_closure(R2, END, R2, 2))
        assert node.counter.counts["added"] == 1 and transforms == []  # neither robot is on the map yet
        node._on_loop_closure(_robot_closure(R1, END, R1, 2))
        (message,) = transforms
        assert [transform.child_frame_id for transform in message.transforms] == ["r1/odom"]  # r2's withheld
        node._on_loop_closure(_robot_closure(R2, 10, R1, 31))
        assert node.counter.counts["added"] == 3
        frames = {transform.child_frame_id: transform for transform in transforms[-1].transforms}
        assert sorted(frames) == ["r1/odom", "r2/odom"]
        assert {transform.header.frame_id for transform in frames.values()} == {"map"}
        moved = frames["r2/odom"].transform.translation
        assert np.allclose([moved.x, moved.y, moved.z], b_offset().translation(), atol=1e-3)
        still = frames["r1/odom"].transform.translation
        assert np.allclose([still.x, still.y, still.z], 0.0, atol=1e-3)
        assert not any(key.startswith("dropped_") for key in node.counter.counts)

        # r2 relocated: its new session's first posterior moves r2's odometry from then on, r1's stays.
        posterior = msg.PlacePosterior(query_id=90, robot="r2", session=1)
        posterior.header.stamp = time_from_ns(r2_stamp(70))
        node._on_posterior(posterior)
        assert node.graph.current_session("r2") == ("r2", 1) and node.graph.current_session("r1") == R1
        assert node.graph.sessions[("r2", 1)].odometry.samples()[0] == [r2_stamp(i) for i in range(70, END + 1)]
        assert node.graph.sessions[R1].odometry.last_ns == stamp(END)
        assert node.close()
    finally:
        node.destroy_node()
    stamps_s = [float(line.split()[0]) for line in trajectory_file.read_text().splitlines()]
    expected_ns = sorted([stamp(0), stamp(2), stamp(31), stamp(END), r2_stamp(0), r2_stamp(2), r2_stamp(10),
                          r2_stamp(END)])
    assert stamps_s == pytest.approx([stamp_ns / 1e9 for stamp_ns in expected_ns])
    assert sorted(path.name for path in tmp_path.iterdir()) == ["keyframes.tum"]  # no session left off the map
