"""aefabmap_msgs messages cross an OS-process boundary over ROS 2 (loopback discovery) intact."""

import json
from pathlib import Path

import pytest

from test.ros_processes import running, write_script

pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

PUBLISHER = """
import sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy
from aefabmap_msgs.msg import Features, LoopClosure
from builtin_interfaces.msg import Time

rclpy.init()
node = rclpy.create_node("ipc_test_publisher")
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
loop_pub = node.create_publisher(LoopClosure, "ipc_test/loop_closures", qos)
feat_pub = node.create_publisher(Features, "ipc_test/features", qos)
loop = LoopClosure()
loop.header.stamp = Time(sec=12, nanosec=345)
loop.header.frame_id = "cam"
loop.query_id, loop.query_place_id, loop.matched_place_id = 40, 3, 3
loop.matched_stamp = Time(sec=2, nanosec=7)
loop.probability, loop.log_likelihood = 0.9975, -31.25
feat = Features()
feat.header.stamp = Time(sec=12, nanosec=345)
feat.descriptor_type = "orb"
feat.image_width, feat.image_height = 640, 480
feat.x, feat.y, feat.size, feat.angle, feat.response = [1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0], [0.5, 0.25]
feat.descriptor_length = 32
feat.binary_descriptors = list(range(64))
deadline = time.monotonic() + 30
while time.monotonic() < deadline:
    loop_pub.publish(loop)
    feat_pub.publish(feat)
    rclpy.spin_once(node, timeout_sec=0.1)
node.destroy_node()
rclpy.try_shutdown()
"""

SUBSCRIBER = """
import json, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy
from aefabmap_msgs.msg import Features, LoopClosure

rclpy.init()
node = rclpy.create_node("ipc_test_subscriber")
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
got = {}
def on_loop(m):
    got["loop"] = dict(stamp=[m.header.stamp.sec, m.header.stamp.nanosec], frame=m.header.frame_id,
        ids=[m.query_id, m.query_place_id, m.matched_place_id],
        matched=[m.matched_stamp.sec, m.matched_stamp.nanosec], p=m.probability, ll=m.log_likelihood)
def on_feat(m):
    got["features"] = dict(type=m.descriptor_type, size=[m.image_width, m.image_height], x=list(m.x),
        y=list(m.y), response=list(m.response), length=m.descriptor_length, binary=list(m.binary_descriptors),
        floats=list(m.float_descriptors))
node.create_subscription(LoopClosure, "ipc_test/loop_closures", on_loop, qos)
node.create_subscription(Features, "ipc_test/features", on_feat, qos)
deadline = time.monotonic() + 40
while len(got) < 2 and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
print(json.dumps(got))
node.destroy_node()
rclpy.try_shutdown()
sys.exit(0 if len(got) == 2 else 1)
"""


@pytest.mark.ros
def test_loop_closure_and_features_cross_processes(tmp_path: Path) -> None:
    subscriber_script = write_script(tmp_path, "sub.py", SUBSCRIBER)
    publisher_script = write_script(tmp_path, "pub.py", PUBLISHER)
    with running(subscriber_script) as subscriber, running(publisher_script):
        stdout, stderr = subscriber.communicate(timeout=60)
    assert subscriber.returncode == 0, f"subscriber got nothing: {stderr[-2000:]}"
    got = json.loads(stdout.strip().splitlines()[-1])
    assert got["loop"] == {
        "stamp": [12, 345], "frame": "cam", "ids": [40, 3, 3], "matched": [2, 7], "p": 0.9975, "ll": -31.25,
    }
    assert got["features"] == {
        "type": "orb", "size": [640, 480], "x": [1.0, 2.0], "y": [3.0, 4.0], "response": [0.5, 0.25],
        "length": 32, "binary": list(range(64)), "floats": [],
    }
