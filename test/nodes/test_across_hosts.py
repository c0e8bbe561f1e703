"""Across hosts: feature_node on one network host, the rest of the suite on another, over a real link.

Two network namespaces joined by a veth pair stand in for a robot and a base station: each has its
own interfaces and addresses, so DDS discovery and data must cross the veth link by UDP (shared
memory is switched off with FASTDDS_BUILTIN_TRANSPORTS=UDPv4, as it would be unavailable between two
machines). Needs root and ``ip netns``; skipped with the reason elsewhere.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from test.revisit_fixture import FRAMES_PER_PASS, RevisitData
from test.ros_processes import LoggedProcess

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@dataclass(frozen=True)
class Host:
    namespace: str
    interface: str  # its end of the link (a robot's veth; a base's bridge)
    address: str

    @property
    def prefix(self) -> list[str]:
        return ["ip", "netns", "exec", self.namespace]


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


@pytest.fixture
def two_hosts() -> Iterator[tuple[Host, Host]]:
    """Namespaces ``robot`` (10.231.0.1) and ``base`` (10.231.0.2) on one /24 over a veth pair."""
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2): cannot make network namespaces")
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (`ip netns add`)")
    tag = f"aefm{os.getpid() % 100000}"
    robot = Host(f"{tag}r", f"{tag}r0", "10.231.0.1")
    base = Host(f"{tag}b", f"{tag}b0", "10.231.0.2")
    created: list[str] = []
    try:
        for host in (robot, base):
            result = _ip("netns", "add", host.namespace)
            if result.returncode != 0:
                pytest.skip(f"cannot create a network namespace here: {result.stderr.strip()}")
            created.append(host.namespace)
        commands: list[tuple[str, ...]] = [
            ("link", "add", robot.interface, "netns", robot.namespace, "type", "veth",
             "peer", "name", base.interface, "netns", base.namespace),
        ]
        for host in (robot, base):
            commands += [
                ("-n", host.namespace, "addr", "add", f"{host.address}/24", "dev", host.interface),
                ("-n", host.namespace, "link", "set", "lo", "up"),
                ("-n", host.namespace, "link", "set", host.interface, "up"),
                # DDS discovery is multicast (239.255.0.1): route it over the link, as a LAN's default route does.
                ("-n", host.namespace, "route", "add", "224.0.0.0/4", "dev", host.interface),
            ]
        for command in commands:
            result = _ip(*command)
            if result.returncode != 0:
                pytest.skip(f"cannot set up the veth link (`ip {' '.join(command)}`): {result.stderr.strip()}")
        yield robot, base
    finally:
        for namespace in created:  # deleting a namespace deletes its end of the veth pair, and so the pair
            _ip("netns", "del", namespace)


def _link_bytes(host: Host) -> int:
    """Bytes sent by ``host`` over its veth end (what crossed the link in that direction)."""
    statistics = Path(f"/sys/class/net/{host.interface}/statistics/tx_bytes")
    result = subprocess.run([*host.prefix, "cat", str(statistics)], capture_output=True, text=True, timeout=10)
    return int(result.stdout)


def test_feature_node_on_another_host_feeds_the_rest_of_the_suite(tmp_path: Path, revisit_data: RevisitData,
                                                                   two_hosts: tuple[Host, Host]) -> None:
    robot, base = two_hosts
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    params = ["-p", f"model_dir:={revisit_data.model_dir}", "-p", "image_qos:=reliable", "-p", "drop_when_busy:=false"]
    with (
        LoggedProcess(tmp_path / "feature.log", "aefabmap_ros.nodes.feature_node", "--ros-args", *params,
                      prefix=robot.prefix, env=env) as feature,
        LoggedProcess(tmp_path / "quantizer.log", "aefabmap_ros.nodes.quantizer_node", "--ros-args", *params,
                      prefix=base.prefix, env=env) as quantizer,
        LoggedProcess(tmp_path / "fabmap.log", "aefabmap_ros.nodes.fabmap_node", "--ros-args", *params,
                      prefix=base.prefix, env=env) as fabmap,
    ):
        feature.wait_for_log("extracting", timeout_s=90)
        quantizer.wait_for_log("quantizing", timeout_s=90)
        fabmap.wait_for_log("FAB-MAP 2 on", timeout_s=90)
        # Discovery across the link takes its time: replay only once the robot's features reach the base
        # (else the first frame's features go out before the quantizer is matched, and are lost).
        quantizer.wait_for_log("receiving features", timeout_s=90)
        fabmap.wait_for_log("receiving words", timeout_s=90)
        sent_before = (_link_bytes(robot), _link_bytes(base))
        # The replay (base) waits until feature_node (robot) subscribed and fabmap_node answers; lockstep: every
        # image must come back as a place posterior, through the robot and back.
        with LoggedProcess(tmp_path / "replay.log", "aefabmap_ros.cli.replay", revisit_data.first_pass_bag,
                           "--topic", "/image", "--lockstep", "place_posteriors", "--lockstep-timeout", "30",
                           "--wait-timeout", "60", "--quiet", prefix=base.prefix, env=env) as replay:
            assert replay.wait(timeout_s=180) == 0, replay.log() + feature.log()
        log = replay.log()
        assert f"published {FRAMES_PER_PASS} images" in log and "0 without an answer" in log, log
        robot_sent = _link_bytes(robot) - sent_before[0]
        base_sent = _link_bytes(base) - sent_before[1]
        # Printed for the README's figures (pytest -s): what crossed the link per image, each way.
        print(f"\n[across hosts] per image: base -> robot {base_sent / FRAMES_PER_PASS / 1024:.1f} KiB (the image), "
              f"robot -> base {robot_sent / FRAMES_PER_PASS / 1024:.1f} KiB (its features)")
        assert base_sent > 0 and robot_sent > 0
