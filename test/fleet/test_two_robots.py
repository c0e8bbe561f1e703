"""Two robots and a base station, each on its own network host, over real links (docs/fleet.md).

Three network namespaces stand in for two robots and a base station: each robot's veth link ends on a bridge
in the base's namespace, all on 10.77.3.0/24 (robot1 .1, robot2 .2, base .3). DDS finds its peers through
ROS_STATIC_PEERS (each robot names the base, the base both robots; no multicast route, so the robots never see
each other) and carries everything over UDP (FASTDDS_BUILTIN_TRANSPORTS=UDPv4: no shared memory across hosts).

Each robot runs its front end (``aefabmap_launch --robot-side --pipeline``) and replays 8 s of one synthetic
town at 10 Hz (2.5 m/s) with depth and camera_info: robot 1 the start of the first lap, robot 2 the same streets
on the second lap (later stamps), started 2 s after robot 1 so that it revisits places robot 1 has just made,
both live at once. The base
(``aefabmap_launch --base``) takes both robots' words into one map, asks each robot for the features it will
verify, and publishes inter-robot closures with a metric pose. Measured: the serialized bytes of every message
that crosses each robot's link (words, requested features, requests), and the bytes the veth interface carried
(DDS's own traffic included), per processed frame and per second; each robot's detection rate at the base;
each closure's pose against the town's ground truth. Needs root and ``ip netns``; skipped with the reason
elsewhere. Printed with ``pytest -s`` (the figures of docs/fleet.md).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("aefabmap_msgs.msg")

from scipy.spatial.transform import Rotation

from aefabmap_ros.datasets.synth.config import SynthConfig
from aefabmap_ros.datasets.synth.renderer import PinholeCamera, camera_effects, render_view_and_depth
from aefabmap_ros.datasets.synth.trajectory import drive_route, poses_from_headings, smooth_series
from aefabmap_ros.datasets.synth.world import build_world
from test.nodes.test_across_hosts import Host, _ip
from test.revisit_fixture import RevisitData
from test.ros_processes import LoggedProcess

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SUBNET = "10.77.3"
FRAMES_PER_LAP = 600  # 0.25 m apart: 2.5 m/s at 10 Hz
FRAMES_PER_STRETCH = 80  # what each robot replays: 8 s, 20 m
TARGET_BYTES_PER_FRAME = 20_000
MIN_RATE_HZ = 3.0
ROBOT2_DELAY_S = 2.0
# The shipped settings but for the odometry gate (no odometry here); AEFABMAP_FLEET_MAX_FEATURES and
# AEFABMAP_FLEET_REQUESTS_PER_FRAME measure other link settings.
PARAMS = """
verifier_node:
  ros__parameters:
    odometry_gate: false
    requests_per_frame: {requests_per_frame}
feature_server_node:
  ros__parameters:
    max_features: {max_features}
"""


def _setup(robots: list[Host], base: Host) -> None:
    commands: list[tuple[str, ...]] = [
        ("-n", base.namespace, "link", "add", base.interface, "type", "bridge"),
        ("-n", base.namespace, "addr", "add", f"{base.address}/24", "dev", base.interface),
        ("-n", base.namespace, "link", "set", base.interface, "up"),
        ("-n", base.namespace, "link", "set", "lo", "up"),
    ]
    for index, robot in enumerate(robots):
        port = f"{base.namespace}p{index}"
        commands += [
            ("link", "add", robot.interface, "netns", robot.namespace, "type", "veth",
             "peer", "name", port, "netns", base.namespace),
            ("-n", base.namespace, "link", "set", port, "master", base.interface),
            ("-n", base.namespace, "link", "set", port, "up"),
            ("-n", robot.namespace, "addr", "add", f"{robot.address}/24", "dev", robot.interface),
            ("-n", robot.namespace, "link", "set", robot.interface, "up"),
            ("-n", robot.namespace, "link", "set", "lo", "up"),
        ]
    for command in commands:
        result = _ip(*command)
        if result.returncode != 0:
            pytest.skip(f"cannot set up the links (`ip {' '.join(command)}`): {result.stderr.strip()}")


@pytest.fixture
def fleet_hosts() -> Iterator[tuple[list[Host], Host]]:
    """Namespaces of robot1, robot2 and the base on one /24, the robots' links bridged at the base."""
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2): cannot make network namespaces")
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (`ip netns add`)")
    tag = f"aeff{os.getpid() % 100000}"
    robots = [Host(f"{tag}r{k}", f"{tag}r{k}v", f"{SUBNET}.{k}") for k in (1, 2)]
    base = Host(f"{tag}b", f"{tag}br", f"{SUBNET}.3")
    created: list[str] = []
    try:
        for host in (*robots, base):
            result = _ip("netns", "add", host.namespace)
            if result.returncode != 0:
                pytest.skip(f"cannot create a network namespace here: {result.stderr.strip()}")
            created.append(host.namespace)
        _setup(robots, base)
        yield robots, base
    finally:
        for namespace in created:  # deleting a namespace deletes its interfaces, the veth pairs with them
            _ip("netns", "del", namespace)


def _link_bytes(host: Host) -> tuple[int, int]:
    """(sent, received) bytes of the host's link interface, as ``ip -s link`` counts them."""
    values = []
    for counter in ("tx_bytes", "rx_bytes"):
        path = f"/sys/class/net/{host.interface}/statistics/{counter}"
        values.append(int(subprocess.run([*host.prefix, "cat", path], capture_output=True, text=True,
                                         timeout=10).stdout))
    return values[0], values[1]


@dataclass(frozen=True)
class Stretches:
    robot_frames: list[Path]  # npz per robot: images, depths, stamps, camera_matrix
    stamps_ns: np.ndarray  # of every frame of the route
    poses: np.ndarray  # (N, 3, 4) camera-to-world, every frame of the route


def _render(config: SynthConfig, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The frames ``indices`` of the town's route as generate_sequence renders them (images, depths), and the
    route's stamps and poses: only what a robot replays is rendered."""
    world = build_world(config)
    motion_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 2]))
    camera_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 3]))
    count = config.num_frames
    positions_xy, headings = drive_route(config, world, motion_rng)
    heights = config.camera_height_m + 0.05 * smooth_series(motion_rng, count, 20.0)
    sun = motion_rng.uniform(0, 2 * np.pi) + np.deg2rad(config.sun_drift_deg) * np.arange(count) / (count - 1)
    variation = config.lighting_variation  # the lighting of each lap, as generate_sequence draws it
    gains = 1.0 + variation * np.tanh(smooth_series(motion_rng, count, count / 6))
    gains *= 1.0 + 0.02 * variation * motion_rng.normal(size=count)
    gammas = 1.0 + 0.5 * variation * np.tanh(smooth_series(motion_rng, count, count / 5))
    camera = PinholeCamera.from_config(config)
    noise = camera_rng.normal(0.0, config.noise_sigma, size=(2 * config.height, 2 * config.width)).astype(np.float32)
    images, depths = [], []
    for index in indices.tolist():
        radiance, depth = render_view_and_depth(world, camera, positions_xy[index], float(headings[index]),
                                                float(heights[index]), float(sun[index]), config.fog_distance_m)
        images.append(camera_effects(radiance, camera_rng, noise, float(gains[index]), float(gammas[index]), config))
        depths.append(depth)
    stamps = config.start_stamp_ns + np.rint(np.arange(count) * (1e9 / config.frame_rate_hz)).astype(np.int64)
    poses = poses_from_headings(np.column_stack([positions_xy, heights]), headings)
    return np.stack(images), np.stack(depths), stamps, poses


def _stretches(directory: Path) -> Stretches:
    """Two laps of the revisit fixture's town (its model's vocabulary was trained on another town) at ~2.5 m/s,
    10 Hz: robot 1 drives the start of the first lap, robot 2 the same streets on the second lap (later
    stamps)."""
    config = SynthConfig(num_frames=2 * FRAMES_PER_LAP, width=320, height=240, laps=2, blur_probability=0.0)
    robot1 = np.arange(FRAMES_PER_STRETCH)
    robot2 = FRAMES_PER_LAP + np.arange(FRAMES_PER_STRETCH)
    images, depths, stamps, poses = _render(config, np.concatenate([robot1, robot2]))
    camera_matrix = PinholeCamera.from_config(config).matrix()
    files = []
    for robot, (indices, rows) in {"robot1": (robot1, slice(0, FRAMES_PER_STRETCH)),
                                   "robot2": (robot2, slice(FRAMES_PER_STRETCH, None))}.items():
        path = directory / f"{robot}.npz"
        np.savez(path, images=images[rows], depths=depths[rows], stamps_ns=stamps[indices], camera_matrix=camera_matrix)
        files.append(path)
    return Stretches(files, stamps, poses)


def _environment(peers: list[Host]) -> dict[str, str]:
    return {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
            "ROS_STATIC_PEERS": ";".join(peer.address for peer in peers), "ROS_DOMAIN_ID": "17",
            "PYTHONPATH": str(Path(__file__).resolve().parents[2])}


def _pose_errors(closure: dict[str, Any], stretches: Stretches) -> tuple[float, float]:
    """(translation error m, rotation error deg) of a closure's pose: the matched camera in the query's frame."""
    def camera(stamp_ns: int) -> np.ndarray:
        index = int(np.searchsorted(stretches.stamps_ns, stamp_ns))
        pose = np.eye(4)
        pose[:3] = stretches.poses[index]
        return pose

    truth = np.linalg.inv(camera(closure["query_ns"])) @ camera(closure["matched_ns"])
    rotation = Rotation.from_quat(closure["rotation_xyzw"]).as_matrix()
    angle = Rotation.from_matrix(rotation @ truth[:3, :3].T).magnitude()
    return float(np.linalg.norm(np.asarray(closure["translation"]) - truth[:3, 3])), float(np.degrees(angle))


def _link_report(robot: str, counted: dict[str, Any], veth: tuple[int, int], frames: int) -> float:
    """Print one robot's link figures; its serialized bytes per processed frame."""
    topics = counted["topics"]
    serialized = sum(topic["bytes"] for topic in topics.values())
    seconds = counted["seconds"]
    parts = ", ".join(f"{name.split('/')[-1]} {t['messages']:.0f} msgs {t['bytes'] / max(frames, 1):.0f} B/frame "
                      f"{t['bytes'] / seconds:.0f} B/s" for name, t in topics.items())
    print(f"\n[fleet] {robot}: {frames} frames processed in {seconds:.1f} s; serialized {serialized / frames:.0f} "
          f"B/frame, {serialized / seconds:.0f} B/s ({parts}); veth sent {veth[0] / frames:.0f} B/frame "
          f"{veth[0] / seconds:.0f} B/s, received {veth[1] / frames:.0f} B/frame {veth[1] / seconds:.0f} B/s")
    return serialized / frames


def test_two_robots_share_one_map_at_a_base_station_over_small_links(
        tmp_path: Path, revisit_data: RevisitData, fleet_hosts: tuple[list[Host], Host]) -> None:
    robots, base = fleet_hosts
    stretches = _stretches(tmp_path)
    params = tmp_path / "params.yaml"
    params.write_text(PARAMS.format(max_features=int(os.environ.get("AEFABMAP_FLEET_MAX_FEATURES", "300")),
                                    requests_per_frame=float(os.environ.get("AEFABMAP_FLEET_REQUESTS_PER_FRAME",
                                                                            "0.4"))))
    model = str(revisit_data.model_dir)
    base_env = _environment(robots)
    go = tmp_path / "go"
    closures_file = tmp_path / "base.jsonl"
    common: list[str | Path] = ["--model", model, "--params", params]
    with (
        LoggedProcess(tmp_path / "base.log", "aefabmap_ros.cli.launch", "--base", "--robots", "robot1,robot2",
                      *common, prefix=base.prefix, env=base_env) as base_nodes,
        LoggedProcess(tmp_path / "recorder.log", "test.fleet.base_recorder", closures_file, prefix=base.prefix,
                      env=base_env) as recorder,
        LoggedProcess(tmp_path / "robot1.log", "aefabmap_ros.cli.launch", "--robot-side", "--robot", "robot1",
                      "--depth-topic", "depth", "--pipeline", *common, prefix=robots[0].prefix,
                      env=_environment([base])) as robot1,
        LoggedProcess(tmp_path / "robot2.log", "aefabmap_ros.cli.launch", "--robot-side", "--robot", "robot2",
                      "--depth-topic", "depth", "--pipeline", *common, prefix=robots[1].prefix,
                      env=_environment([base])) as robot2,
    ):
        drivers = [LoggedProcess(tmp_path / f"driver{k}.log", "test.fleet.robot_driver", "--robot", f"robot{k}",
                                 "--frames", stretches.robot_frames[k - 1], "--go", go, "--delay",
                                 str(ROBOT2_DELAY_S * (k - 1)), "--out", tmp_path / f"robot{k}.json",
                                 prefix=robots[k - 1].prefix, env=_environment([base])) for k in (1, 2)]
        try:
            for line in ("receiving words of robot1", "receiving words of robot2",
                         "receiving requested features of robot1", "receiving requested features of robot2"):
                base_nodes.wait_for_log(line, timeout_s=120)
            recorder.wait_for_log("[recorder] recording", timeout_s=60)
            for driver in drivers:
                driver.wait_for_log("[driver] ready", timeout_s=120)
            before = [_link_bytes(robot) for robot in robots]
            go.touch()
            for driver in drivers:
                assert driver.wait(timeout_s=120) == 0, driver.log()
            after = [_link_bytes(robot) for robot in robots]
        finally:
            for driver in drivers:
                driver.__exit__()
        assert robot1.stop() == 0 and robot2.stop() == 0, robot1.log()[-3000:] + robot2.log()[-3000:]
        assert base_nodes.stop() == 0, base_nodes.log()[-3000:]
        recorder.stop()
    records = [json.loads(line) for line in closures_file.read_text().splitlines()]
    veth = [(a[0] - b[0], a[1] - b[1]) for a, b in zip(after, before, strict=True)]
    _check_results(records, stretches, veth, tmp_path, base_nodes.log(), [robot1.log(), robot2.log()])


def _check_results(records: list[dict[str, Any]], stretches: Stretches, veth: list[tuple[int, int]],
                   tmp_path: Path, base_log: str, robot_logs: list[str]) -> None:
    """Print every figure first (pytest -s), then check them."""
    per_frame, rates, frames = {}, {}, {}
    for k, name in enumerate(("robot1", "robot2")):
        counted = json.loads((tmp_path / f"{name}.json").read_text())
        frames[name] = int(counted["topics"]["aefabmap/words"]["messages"])
        assert frames[name] >= FRAMES_PER_STRETCH // 2, robot_logs[k][-3000:]
        per_frame[name] = _link_report(name, counted, veth[k], frames[name])
        received = [r["received_s"] for r in records if r["kind"] == "posterior" and r["robot"] == name]
        rates[name] = (len(received) - 1) / (received[-1] - received[0])
        print(f"[fleet] {name}: {len(received)} posteriors at the base, {rates[name]:.1f} Hz")
    closures = [r for r in records if r["kind"] == "closure"]
    inter = [c for c in closures if c["query_robot"] != c["matched_robot"]]
    posed = [c for c in inter if c["pose_available"]]
    errors = [_pose_errors(c, stretches) for c in posed]
    for closure, (metres, degrees) in zip(posed, errors, strict=True):
        print(f"[fleet] {closure['query_robot']} {closure['query_ns']} -> {closure['matched_robot']} "
              f"{closure['matched_ns']}: {closure['inliers']} inliers, metric {closure['translation_metric']}, "
              f"pose error {metres:.3f} m {degrees:.2f} deg")
    print(f"[fleet] {len(closures)} closures, {len(inter)} between the robots, {len(errors)} with a pose")
    for name in per_frame:
        assert per_frame[name] <= TARGET_BYTES_PER_FRAME, f"{name}: {per_frame[name]:.0f} B per frame"
        # docs/fleet.md's target is 5 Hz on an otherwise idle 2-core machine; shared, it only has to keep going.
        assert rates[name] >= MIN_RATE_HZ, f"{name}: {rates[name]:.1f} Hz"
    assert inter and all(c["query_robot"] == "robot2" and c["matched_robot"] == "robot1" for c in inter), closures
    assert errors and all(c["translation_metric"] for c in posed)
    assert np.median([metres for metres, _ in errors]) < 0.5 and max(d for _, d in errors) < 10.0, errors
    assert "dropped_robot_mismatch" not in base_log and "dropped_stamp_of_another_robot" not in base_log
