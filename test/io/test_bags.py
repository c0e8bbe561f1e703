"""rosbags round trips of sensor_msgs/Image and the suite's own message types, mcap and sqlite3."""

from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.errors import BagError
from aefabmap_ros.io import bag_messages, bags
from aefabmap_ros.stamps import stamp_to_ns


def _frames(count: int) -> list[tuple[int, np.ndarray]]:
    rng = np.random.default_rng(0)
    return [(1_000_000_000 + i * 100_000_000, rng.integers(0, 255, (12, 16), dtype=np.uint8)) for i in range(count)]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_image_bag_round_trip(tmp_path: Path, storage: str) -> None:
    frames = _frames(5)
    path = tmp_path / "images"
    assert bags.write_image_bag(path, "/cam/image", frames, storage=storage) == 5
    assert bags.list_topics(path) == {"/cam/image": bag_messages.IMAGE_TYPE}
    read = list(bags.read_messages(path, ["/cam/image"]))
    assert [m.stamp_ns for m in read] == [stamp for stamp, _ in frames]
    for message, (_, image) in zip(read, frames, strict=True):
        assert message.message.encoding == "mono8"
        np.testing.assert_array_equal(np.asarray(message.message.data).reshape(12, 16), image)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_custom_types_round_trip(tmp_path: Path, storage: str) -> None:
    types = bag_messages.get_typestore().types
    loop = types["aefabmap_msgs/msg/LoopClosure"](
        header=bag_messages.make_header(5_000_000_123, "cam"),
        query_id=42,
        query_place_id=7,
        matched_place_id=7,
        matched_stamp=bag_messages.make_time(1_000_000_456),
        probability=0.995,
        log_likelihood=-12.5,
        inliers=37,
        **bag_messages.no_pose_fields(),
        query_robot="r2",
        query_session=1,
        matched_robot="",
        matched_session=0,
    )
    features = types["aefabmap_msgs/msg/Features"](
        header=bag_messages.make_header(5_000_000_123, "cam"),
        descriptor_type="sift",
        image_width=640,
        image_height=480,
        x=np.array([1.5, 2.5], np.float32),
        y=np.array([3.0, 4.0], np.float32),
        size=np.array([2.0, 3.0], np.float32),
        angle=np.array([10.0, 20.0], np.float32),
        response=np.array([0.1, 0.2], np.float32),
        descriptor_length=3,
        float_descriptors=np.arange(6, dtype=np.float32),
        binary_descriptors=np.zeros(0, np.uint8),
    )
    path = tmp_path / "out"
    with bags.BagWriter(path, storage=storage) as writer:
        writer.add_topic("/loop_closures", "aefabmap_msgs/msg/LoopClosure")
        writer.add_topic("/aefabmap/features", "aefabmap_msgs/msg/Features")
        writer.add_topic("/image", bag_messages.IMAGE_TYPE)
        writer.write("/loop_closures", 5_000_000_123, loop)
        writer.write("/aefabmap/features", 5_000_000_123, features)
        image = bag_messages.make_image_message(np.zeros((4, 4, 3), np.uint8), 5_000_000_123)
        writer.write("/image", 5_000_000_123, image)
    read = {m.topic: m.message for m in bags.read_messages(path, ["/loop_closures", "/aefabmap/features", "/image"])}
    got_loop = read["/loop_closures"]
    assert (got_loop.query_id, got_loop.matched_place_id, got_loop.probability, got_loop.inliers) == (42, 7, 0.995, 37)
    assert stamp_to_ns(got_loop.matched_stamp) == 1_000_000_456
    assert got_loop.header.frame_id == "cam"
    got_features = read["/aefabmap/features"]
    np.testing.assert_array_equal(got_features.float_descriptors, np.arange(6, dtype=np.float32))
    np.testing.assert_array_equal(got_features.x, [1.5, 2.5])
    assert got_features.descriptor_type == "sift"
    assert read["/image"].encoding == "bgr8"


def test_writer_is_atomic_on_error(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    with pytest.raises(RuntimeError), bags.BagWriter(path) as writer:
        writer.add_topic("/image", bag_messages.IMAGE_TYPE)
        raise RuntimeError("interrupted")
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


def test_refuses_existing_output(tmp_path: Path) -> None:
    bags.write_image_bag(tmp_path / "bag", "/image", _frames(1))
    with pytest.raises(BagError, match="already exists"):
        bags.write_image_bag(tmp_path / "bag", "/image", _frames(1))
    assert bags.write_image_bag(tmp_path / "bag", "/image", _frames(2), overwrite=True) == 2


def test_missing_bag_and_topic(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="does not exist"):
        bags.list_topics(tmp_path / "nope")
    bags.write_image_bag(tmp_path / "bag", "/image", _frames(1))
    with pytest.raises(BagError, match=r"'/camera' not in bag .* image topics: \['/image'\]"):
        bags.require_image_topic(tmp_path / "bag", "/camera")
    with pytest.raises(BagError, match="not in bag"):
        list(bags.read_messages(tmp_path / "bag", ["/other"]))


def test_corrupt_bag(tmp_path: Path) -> None:
    path = tmp_path / "bag"
    bags.write_image_bag(path, "/image", _frames(20))
    mcap_file = next(path.glob("*.mcap"))
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match="bag"):
        list(bags.read_messages(path, ["/image"]))
    (path / "metadata.yaml").write_text("not: [valid")
    with pytest.raises(BagError, match="cannot open bag"):
        bags.list_topics(path)


def test_unknown_storage(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="unknown bag storage 'zip'"):
        bags.BagWriter(tmp_path / "bag", storage="zip")


def test_rgbd_bag_round_trip(tmp_path: Path) -> None:
    image = np.arange(12, dtype=np.uint8).reshape(3, 4)
    depth = np.array([[0, 1, 65535, 1000], [2, 3, 4, 5], [6, 7, 8, 9]], dtype=np.uint16)
    camera = np.array([[100.0, 0.0, 1.5], [0.0, 101.0, 1.0], [0.0, 0.0, 1.0]])
    frames = [(1_000, image, depth), (2_000, image + 1, depth + 1)]
    assert bags.write_rgbd_bag(tmp_path / "bag", "/cam/image", frames, camera) == 2
    assert bags.list_topics(tmp_path / "bag") == {
        "/cam/image": bag_messages.IMAGE_TYPE, "/cam/depth": bag_messages.IMAGE_TYPE,
        "/cam/camera_info": bag_messages.CAMERA_INFO_TYPE}
    messages = list(bags.read_messages(tmp_path / "bag", ["/cam/image", "/cam/depth", "/cam/camera_info"]))
    assert [m.stamp_ns for m in messages] == [1_000] * 3 + [2_000] * 3
    by_topic = {m.topic: m.message for m in messages[:3]}
    stored = by_topic["/cam/depth"]
    assert (stored.encoding, stored.step, stored.is_bigendian) == ("16UC1", 8, 0)
    np.testing.assert_array_equal(np.frombuffer(bytes(stored.data), "<u2").reshape(3, 4), depth)
    info = by_topic["/cam/camera_info"]
    assert (info.width, info.height, info.distortion_model) == (4, 3, "plumb_bob")
    np.testing.assert_array_equal(np.asarray(info.k).reshape(3, 3), camera)
    np.testing.assert_array_equal(np.asarray(info.p).reshape(3, 4)[:, :3], camera)


def test_sibling_topics() -> None:
    assert bags.sibling_topic("/camera/image_raw", "depth") == "/camera/depth"
    assert bags.sibling_topic("/image", "camera_info") == "/camera_info"
    assert bags.sibling_topic("image", "depth") == "/depth"


def test_rgbd_bag_errors(tmp_path: Path) -> None:
    image = np.zeros((3, 4), np.uint8)
    with pytest.raises(BagError, match=r"frame 0: depth must be uint16 \(3, 4\), got float32 \(3, 4\)"):
        bags.write_rgbd_bag(tmp_path / "a", "/image", [(1, image, np.zeros((3, 4), np.float32))], np.eye(3))
    assert not (tmp_path / "a").exists()
    with pytest.raises(BagError, match=r"camera_matrix must be a finite \(3, 3\) array, got shape \(2, 2\)"):
        bags.write_rgbd_bag(tmp_path / "b", "/image", [(1, image, np.zeros((3, 4), np.uint16))], np.eye(2))
    with pytest.raises(BagError, match="got int32 \\(3, 4\\)"):
        bag_messages.make_image_message(np.zeros((3, 4), np.int32), 0)


@pytest.mark.parametrize(("storage", "extension"), [("mcap", "mcap"), ("sqlite3", "db3")])
def test_finished_bag_is_named_as_rosbag2_names_it(tmp_path: Path, storage: str, extension: str) -> None:
    """A finished bag holds <name>_0.<ext> and metadata.yaml naming it: nothing hidden, nothing left beside it
    (a hidden data file is skipped by `cp bag/* dest` and looks like an unfinished recording)."""
    import yaml

    path = tmp_path / "run"
    bags.write_image_bag(path, "/image", _frames(3), storage=storage)
    assert sorted(p.name for p in path.iterdir()) == sorted(["metadata.yaml", f"run_0.{extension}"])
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == [f"run_0.{extension}"]
    assert [f["path"] for f in info["files"]] == [f"run_0.{extension}"]
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # no staging folder left beside it
    assert len(list(bags.read_messages(path, ["/image"]))) == 3


# LoopClosure as recorded before the relative-pose fields were added.
OLD_LOOP_CLOSURE = """std_msgs/Header header
int64 query_id
int64 query_place_id
int64 matched_place_id
builtin_interfaces/Time matched_stamp
float64 probability
float64 log_likelihood
int32 inliers -1
"""


def test_an_older_loop_closure_recording_stays_readable(tmp_path: Path) -> None:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    old = get_typestore(Stores.ROS2_JAZZY)
    old.register(get_types_from_msg(OLD_LOOP_CLOSURE, "aefabmap_msgs/msg/LoopClosure"))
    message = old.types["aefabmap_msgs/msg/LoopClosure"](
        header=bag_messages.make_header(5_000_000_123, "cam"), query_id=42, query_place_id=7, matched_place_id=7,
        matched_stamp=bag_messages.make_time(1_000_000_456), probability=0.995, log_likelihood=-12.5, inliers=37)
    path = tmp_path / "old"
    with bags.BagWriter(path) as writer:
        writer._typestore = old  # what the recorder of that time embedded and serialized
        writer.add_topic("/loop_closures", "aefabmap_msgs/msg/LoopClosure")
        writer.write("/loop_closures", 5_000_000_123, message)
    (read,) = bags.read_messages(path, ["/loop_closures"])
    assert read.message.query_id == 42 and read.message.inliers == 37
    assert read.stamp_ns == 5_000_000_123
