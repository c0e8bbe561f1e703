"""aefabmap_replay: publish a rosbag2 bag's image topic through rclpy (there is no ros2 bag wheel).

Messages go out as the bag's own CDR bytes, with their original header stamps, paced by the bag's
log times divided by ``--rate``. ``--lockstep TOPIC`` publishes the next image only once the
pipeline answered the previous one on TOPIC (e.g. place_posteriors), or announced it skipped on
``--lockstep-skipped`` (feature_node's detection rate), so a replay is lossless and its results
reproducible on any machine, however slow.

``--with TOPIC`` (repeatable) also publishes another topic of the bag, on the same name, in bag
order: each message goes out before the image with the same or a later log time (e.g. a frame's
depth, CameraInfo and odometry before its image), so the nodes have them when the image's results
come. The image stays what --rate and --lockstep pace.

The summary counts what may not have arrived: images published while no subscriber was matched,
lockstep images never answered, and (reliable QoS) whether every subscriber acknowledged the last
ones. Ctrl-C or SIGTERM stops it cleanly, with the summary and the number of images left unpublished:
exit code 130 (SIGINT) or 143 (SIGTERM), or 0 when the stop came after every image was published.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from aefabmap_ros.cli.common import ArgumentParser, parse_or_report, ros_message_class
from aefabmap_ros.cli.replay_messages import companion_types, laps, publish_topic, restamped
from aefabmap_ros.errors import AefabmapError, ConfigError
from aefabmap_ros.io import bag_messages, bags


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="aefabmap_replay", description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", type=Path, help="rosbag2 bag directory (mcap or sqlite3)")
    parser.add_argument("--topic", default="/image", help="image topic in the bag (default: /image)")
    parser.add_argument("--out-topic", default="image",
                        help="image topic to publish on (default: image); a CompressedImage topic goes to "
                        "OUT_TOPIC/compressed, where image_transport and feature_node listen for it")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="playback speed factor; 0 = as fast as possible (default: 1.0)")
    parser.add_argument("--start", type=float, default=0.0, help="skip the first START seconds of the bag")
    parser.add_argument("--loop", action="store_true",
                        help="replay forever; each lap's stamps (its --with topics' too) are shifted past the "
                        "previous lap's")
    parser.add_argument("--qos", choices=("reliable", "sensor_data"), default="reliable",
                        help="publisher QoS (default: reliable)")
    parser.add_argument("--wait-subscribers", type=int, default=1,
                        help="wait for this many subscribers before starting (default: 1; 0 = don't wait)")
    parser.add_argument("--wait-timeout", type=float, default=30.0, help="seconds to wait for subscribers")
    parser.add_argument("--lockstep", metavar="TOPIC", default="",
                        help="after each image, wait for one message on TOPIC (e.g. place_posteriors)")
    parser.add_argument("--lockstep-skipped", metavar="TOPIC", default="aefabmap/skipped_frames",
                        help="with --lockstep: a message here (std_msgs/Header) answers an image too: feature_node "
                        "announces the frames it skips by its detection rate there (default: aefabmap/skipped_frames)")
    parser.add_argument("--lockstep-timeout", type=float, default=10.0,
                        help="seconds to wait for the lockstep answer before moving on (default: 10)")
    parser.add_argument("--queue-depth", type=int, default=100,
                        help="publisher history depth: raise it for --rate 0 bursts into slow subscribers")
    parser.add_argument("--with", dest="companions", action="append", default=[], metavar="TOPIC[=N]",
                        help="also publish this bag topic (same name), each message before the image with "
                        "the same or a later log time; repeatable (e.g. /depth /camera_info /odom); =N: wait "
                        "for N subscribers on it (default: the ones discovered, if any, for up to 5 s)")
    parser.add_argument("--quiet", action="store_true", help="no per-image progress")
    return parser


def _validate(args: argparse.Namespace) -> None:
    if args.rate < 0:
        raise ConfigError(f"--rate must be >= 0, got {args.rate}")
    if args.start < 0:
        raise ConfigError(f"--start must be >= 0, got {args.start}")
    if args.loop and args.lockstep:
        raise ConfigError("--loop and --lockstep together would never end; choose one")
    if args.topic in companion_subscribers(args.companions):
        raise ConfigError(f"--with {args.topic} is the image topic itself")


def companion_subscribers(values: list[str]) -> dict[str, int | None]:
    """--with values -> topic: subscribers to wait for (None: those discovered); ConfigError for a bad count."""
    wanted: dict[str, int | None] = {}
    for value in values:
        topic, separator, count = value.partition("=")
        if separator and (not count.isdigit() or int(count) < 1):
            raise ConfigError(f"--with {value}: the subscriber count after '=' must be an integer >= 1")
        wanted[topic] = int(count) if separator else None
    return wanted


# With --loop, each lap's stamps follow the previous lap's last one by this much (stamps must keep increasing).
LAP_GAP_NS = 100_000_000

# How long the end of a reliable replay waits for every subscriber to acknowledge the last images.
ACK_TIMEOUT_S = 5.0
# A publisher counts a subscriber as matched once it has discovered it; the subscriber may discover the publisher
# a few hundred milliseconds later, and until then drops best-effort messages from it without counting them lost
# (it never knew they were sent): a live test lost its first 6 frames of 30 Hz that way. The replay waits this
# long after the match before its first message.
SUBSCRIBER_DISCOVERY_S = 0.5


class StopRequest:
    """SIGINT/SIGTERM only set a flag that the replay's loops check: no exception at an arbitrary line,
    so no traceback, and the summary of what was (not) published is still printed."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __call__(self, signum: int, _frame: FrameType | None) -> None:
        self.signum = signum

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def install(self) -> None:
        self._previous = {signum: signal.signal(signum, self) for signum in (signal.SIGINT, signal.SIGTERM)}

    def restore(self) -> None:
        """The handlers from before ``install`` (main() may run inside another program, e.g. a test)."""
        for signum, handler in getattr(self, "_previous", {}).items():
            signal.signal(signum, handler)

    def exit_code(self) -> int:
        """The shell's convention for a process ended by a signal: 128 + its number (130, 143)."""
        return 128 + (self.signum or 0)


@dataclass
class Delivery:
    """What a replay published, and what it knows was (maybe) not delivered."""

    published: int = 0
    without_subscriber: int = 0  # published while no subscriber was matched: lost
    missed_answers: int = 0  # --lockstep: no answer within the timeout (dropped or late)
    acknowledged: bool | None = None  # reliable QoS: every subscriber acknowledged the last images

    def summary(self, lockstep_topic: str) -> str:
        parts = [f"{self.without_subscriber} published with no subscriber matched"]
        if lockstep_topic:
            parts.append(f"{self.missed_answers} without an answer on {lockstep_topic}")
        if self.acknowledged is False:
            parts.append(f"the last ones not acknowledged by every subscriber within {ACK_TIMEOUT_S:.0f} s")
        return ", ".join(parts)


class Replayer:
    def __init__(self, args: argparse.Namespace, msgtype: str, stop: StopRequest) -> None:
        import rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import CompressedImage, Image

        self.rclpy = rclpy
        self.stop = stop
        self.args = args
        self.msgtype = msgtype
        self.node = rclpy.create_node("aefabmap_replay")
        msg_class = Image if msgtype == bag_messages.IMAGE_TYPE else CompressedImage
        qos: Any = (qos_profile_sensor_data if args.qos == "sensor_data"
                    else QoSProfile(depth=args.queue_depth, reliability=ReliabilityPolicy.RELIABLE))
        self.publisher = self.node.create_publisher(msg_class, publish_topic(args.out_topic, msgtype), qos)
        self.companion_subscribers = companion_subscribers(args.companions)
        self.companions = {topic: self.node.create_publisher(ros_message_class(msgtype), topic, qos)
                           for topic, msgtype in companion_types(args.bag, list(self.companion_subscribers)).items()}
        self.answers = 0
        if args.lockstep:
            from aefabmap_msgs.msg import PlacePosterior
            from std_msgs.msg import Header

            self.answer_subscription = self.node.create_subscription(
                PlacePosterior, args.lockstep, self._on_answer, 100, raw=True)
            if args.lockstep_skipped:  # each image is answered once: a posterior, or its announced skip
                self.skipped_subscription = self.node.create_subscription(
                    Header, args.lockstep_skipped, self._on_answer, 1000, raw=True)

    def _on_answer(self, _message: bytes) -> None:
        self.answers += 1

    def wait_for_subscribers(self) -> None:
        wanted = self.args.wait_subscribers
        print(f"[replay] waiting for {wanted} subscriber(s) on {self.publisher.topic_name}",
              file=sys.stderr, flush=True)
        deadline = time.monotonic() + self.args.wait_timeout
        while self.publisher.get_subscription_count() < wanted and not self.stop.requested:
            if time.monotonic() > deadline:
                raise AefabmapError(
                    f"no subscriber on {self.publisher.topic_name} after {self.args.wait_timeout:.0f} s "
                    f"(wanted {wanted}); {self._why_no_subscriber()}"
                )
            self.rclpy.spin_once(self.node, timeout_sec=0.05)
        for topic, publisher in self.companions.items():
            # Every subscriber must be matched, or the first messages are lost to it (a backend without its first
            # odometry). Without a count: the ones discovered so far (a topic nobody listens to is not waited
            # for; a subscriber not yet discovered is missed: give the count when it matters).
            wanted = self.companion_subscribers[topic]
            if wanted is not None:
                ready = self._spin_until(lambda p=publisher, n=wanted: p.get_subscription_count() >= n,
                                         self.args.wait_timeout)
            else:
                ready = self._spin_until(lambda p=publisher, t=topic: 0 < self.node.count_subscribers(t)
                                         <= p.get_subscription_count(), min(self.args.wait_timeout, 5.0))
            if not ready:
                print(f"[replay] --with {topic}: {publisher.get_subscription_count()} of "
                      f"{self.node.count_subscribers(topic)} subscriber(s) matched, publishing anyway",
                      file=sys.stderr, flush=True)
        if self.args.lockstep:
            # The answer topic must be connected too, or the first answer is lost: a publisher in the graph
            # (count_publishers) is not yet a matched one, which a just-restarted node showed.
            self._spin_until(lambda: self.answer_subscription.get_publisher_count() > 0, self.args.wait_timeout)
            if self.args.lockstep_skipped:
                self._spin_until(lambda: self.skipped_subscription.get_publisher_count() > 0, 5.0)
        self._spin_until(lambda: False, SUBSCRIBER_DISCOVERY_S)  # returns at once on a stop request

    def _why_no_subscriber(self) -> str:
        """Name subscribers of another message type on our topic (they never match us), else the usual cause."""
        topic = self.publisher.topic_name
        ours = self.msgtype.replace("/msg/", "/")
        subscribers = self.node.get_subscriptions_info_by_topic(topic)
        others = sorted({info.topic_type.replace("/msg/", "/") for info in subscribers} - {ours})
        if others:
            return (f"{topic} has subscriber(s) of type {', '.join(others)}, but {self.args.topic} in the bag is "
                    f"{ours}, so they never connect (a CompressedImage topic is published on OUT_TOPIC/compressed)")
        return "is the pipeline running?"

    def _spin_until(self, done: Callable[..., bool], timeout_s: float) -> bool:
        """Spin until ``done()``; False on timeout or on a stop request."""
        deadline = time.monotonic() + timeout_s
        while not done():
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self.stop.requested:
                return False
            self.rclpy.spin_once(self.node, timeout_sec=min(0.05, remaining))
        return True

    def run(self) -> int:
        args = self.args
        start_ns = None
        if args.start > 0:
            start_ns = next(iter(bags.read_messages(args.bag, [args.topic]))).log_time_ns + int(args.start * 1e9)
        delivery = Delivery()
        finished = False  # every image published: a stop after that is no early stop
        wall_start = time.monotonic()
        lap_span_ns, lap_origin_ns = 0, None
        print(f"[replay] publishing {args.topic} of {args.bag} on {self.publisher.topic_name}", file=sys.stderr,
              flush=True)
        for lap, message in laps(args.bag, args.topic, start_ns, args.loop, list(self.companion_subscribers)):
            if self.stop.requested:
                break
            if message.topic != args.topic:  # moved by its lap's offset, as its image will be
                self.companions[message.topic].publish(
                    restamped(message.raw, message.msgtype, lap * (lap_span_ns + LAP_GAP_NS)))
                continue
            if lap_origin_ns is None:
                lap_origin_ns = message.log_time_ns
            bag_offset_ns = message.log_time_ns - lap_origin_ns
            lap_span_ns = max(lap_span_ns, bag_offset_ns)
            elapsed_bag_s = (lap * (lap_span_ns + 1) + bag_offset_ns) / 1e9
            stamp_offset_ns = lap * (lap_span_ns + LAP_GAP_NS)
            if not self._publish_image(message.raw, delivery, wall_start + elapsed_bag_s / args.rate
                                       if args.rate > 0 else None, stamp_offset_ns):
                break
        else:
            finished = True
        return self._finish(delivery, wall_start, finished)

    def _publish_image(self, raw: bytes, delivery: Delivery, due: float | None, stamp_offset_ns: int) -> bool:
        """Publish one image at its ``due`` monotonic time (None: at once) and, with --lockstep, wait for its
        answer; False when a stop was requested meanwhile."""
        args = self.args
        if due is not None and not args.lockstep:
            self._spin_until(lambda: time.monotonic() >= due, 3600.0)
            if self.stop.requested:
                return False
        if self.publisher.get_subscription_count() == 0:
            delivery.without_subscriber += 1
        self.publisher.publish(restamped(raw, self.msgtype, stamp_offset_ns))
        delivery.published += 1
        if args.lockstep and not self._spin_until(lambda n=delivery.published: self.answers >= n,
                                                  args.lockstep_timeout):
            if self.stop.requested:
                return False
            delivery.missed_answers += 1
            self.answers = delivery.published  # resynchronise: the pipeline dropped this image
        if not args.quiet and delivery.published % 50 == 0:
            print(f"[replay] {delivery.published} images", file=sys.stderr)
        return True

    def _finish(self, delivery: Delivery, wall_start: float, finished: bool) -> int:
        """Wait for the last acknowledgements, print the summary; the exit code."""
        from rclpy.duration import Duration

        args = self.args
        if args.qos == "reliable" and not self.stop.requested:
            # Reliable delivery of the last messages must complete before the node goes away, the --with
            # topics' too: the images may be acknowledged (or have no subscriber) long before the companions'
            # last messages are.
            delivery.acknowledged = all([publisher.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S))
                                         for publisher in (self.publisher, *self.companions.values())])
        seconds = time.monotonic() - wall_start
        print(f"[replay] published {delivery.published} images from {args.bag} {args.topic} in {seconds:.1f} s "
              f"({delivery.summary(args.lockstep)})", file=sys.stderr)
        if finished:
            return 0
        left = ""
        if not args.loop and args.start == 0:
            left = f"; {bags.message_count(args.bag, args.topic) - delivery.published} images of the bag not published"
        print(f"[replay] stopped by {signal.Signals(self.stop.signum or 0).name}{left}", file=sys.stderr)
        return self.stop.exit_code()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    raw_argv = sys.argv[1:] if argv is None else argv
    ros_args: list[str] = []
    if "--ros-args" in raw_argv:
        cut = raw_argv.index("--ros-args")
        raw_argv, ros_args = raw_argv[:cut], raw_argv[cut:]
    args = parse_or_report(parser, raw_argv)
    if args is None:
        return 1
    stop = StopRequest()
    stop.install()  # before anything slow: a signal during start-up is a clean stop too
    try:
        return _replay(args, ros_args, stop)
    finally:
        stop.restore()


def _replay(args: argparse.Namespace, ros_args: list[str], stop: StopRequest) -> int:
    try:
        _validate(args)
        msgtype = bags.require_image_topic(args.bag, args.topic)
    except AefabmapError as exc:
        print(f"ERROR: {exc}", file=sys.stderr)
        return 1

    import rclpy
    from rclpy.signals import SignalHandlerOptions

    # rclpy's own handlers would shut the context down under a running spin (a traceback); ours stop the loops.
    rclpy.init(args=["aefabmap_replay", *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    replayer = None
    try:
        replayer = Replayer(args, msgtype, stop)
        if args.wait_subscribers > 0:
            replayer.wait_for_subscribers()
        if stop.requested:
            print(f"[replay] stopped by {signal.Signals(stop.signum or 0).name} before publishing", file=sys.stderr)
            return stop.exit_code()
        return replayer.run()
    except AefabmapError as exc:
        print(f"ERROR: {exc}", file=sys.stderr)
        return 1
    finally:
        if replayer is not None:
            replayer.node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    raise SystemExit(main())
