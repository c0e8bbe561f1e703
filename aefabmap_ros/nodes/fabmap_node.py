"""fabmap_node: ``aefabmap/words`` -> ``loop_closure_candidates`` and ``place_posteriors`` (FAB-MAP 2).

Its loop closures are FAB-MAP's raw decisions (``inliers`` -1: not verified) on
``loop_closure_candidates``; verifier_node checks them geometrically and publishes those that pass
on ``loop_closures``. Without a verifier, remap ``loop_closure_candidates:=loop_closures``
(``aefabmap_launch --no-verify``, ``verify:=false`` in the launch file).

Keeps the map of places; saves it atomically every ``save_period_s`` (when it changed) and on
shutdown, and reloads it on start, so a restart loses no saved place. A map made with another
vocabulary is refused at start-up rather than silently mixed; one made with other FAB-MAP
settings is used, with a warning naming them. Temporaries a killed save left beside the map are
deleted at start. A frame stamped more than ``max_future_stamp_s`` ahead of the node's clock is
dropped (counted): it would make every later frame "out of order", and, saved in the map, would
do so after every restart too. A map saved before that rule may hold such places: they are kept,
named in a warning at start, and do not order later frames.

Every frame that reaches the node is answered on ``place_posteriors``: a dropped one (already
mapped before a restart, out of order, in the future, malformed) with ``query_id`` -1 and no places.

Sessions: the node works in one session of robot ``robot`` (fabmap/sessions.py). Started on a saved map, it
begins a new session of that map; the service ``~/start_session`` (``std_srvs/Trigger``) begins another one
from the next frame on, for a robot that was relocated (its odometry restarted) while the node ran. Every
posterior and candidate says its query's session and robot and each place's.

Several robots (docs/fleet.md): with ``robots`` (a base station), the node takes each robot's words from
``/<robot>/aefabmap/words`` into the one map, each frame recognised as that robot's (fabmap/robot_track.py); a
frame is "out of order" or "already mapped" against its own robot's newest frame (clocks of different robots
need not interleave). A robot's first frame starts its session; a message naming a robot on
``~/start_robot_session`` (``std_msgs/String``) begins a new session of that robot from its next frame, as
``~/start_session`` does for ``robot``.

While running, the settings of ``detector.RUNTIME_SETTINGS`` (e.g. ``match_threshold``) can be
changed with ``ros2 param set``; any other change is refused with the reason.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from aefabmap_msgs.msg import BagOfWords, LoopClosure, PlacePosterior
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from aefabmap_ros.errors import AefabmapError, ConfigError, ModelError
from aefabmap_ros.fabmap.chowliu import ChowLiuTree
from aefabmap_ros.fabmap.config import FabMapConfig
from aefabmap_ros.fabmap.index import warm_up_kernels
from aefabmap_ros.fabmap.map_file import ConfigDifferences
from aefabmap_ros.fabmap.recognizer import RUNTIME_SETTINGS, PlaceRecognizer, Recognition
from aefabmap_ros.io.atomic import remove_stale_temporaries
from aefabmap_ros.model.directory import load_model
from aefabmap_ros.nodes.common import (
    RESULT_QOS,
    DropCounter,
    PeriodicSave,
    RuntimeParameters,
    counted_subscription,
    declare_config,
    declare_parameter,
    node_callback,
    pipeline_qos,
    report_when_connected,
    run_node,
)
from aefabmap_ros.nodes.fleet_parameters import declare_robots, robot_topic
from aefabmap_ros.nodes.future_stamps import FutureStamps
from aefabmap_ros.nodes.messages import (
    header_stamp_problem,
    message_to_word_ids,
    recognition_to_loop_closure,
    recognition_to_posterior,
    unrecognised_posterior,
)
from aefabmap_ros.stamps import newest_stamp_up_to, stamp_to_ns


class FabMapNode(Node):
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("fabmap_node", **node_kwargs)
        model_dir = declare_parameter(self, "model_dir", "", "Model directory (from aefabmap_train). Required.")
        map_file = declare_parameter(
            self, "map_file", "", "File the map of places is saved to and reloaded from ('' = keep it in memory only)."
        )
        save_period_s = declare_parameter(
            self, "save_period_s", 10.0, "Save the map this often when it changed (seconds; 0 = only on shutdown)."
        )
        depth = declare_parameter(self, "queue_depth", 100, "Queue depth of the words subscription.")
        robot = declare_parameter(self, "robot", "", "Name of the robot whose images this node recognises; kept "
                                  "with every session of the map ('' = a map of one robot).")
        self.robots = declare_robots(self)
        self.future_stamps = FutureStamps(self)
        config = declare_config(self, FabMapConfig)
        if not model_dir:
            raise ConfigError("fabmap_node: parameter model_dir is required (a directory made by aefabmap_train)")
        model = load_model(model_dir)
        if model.tree_matrix is None or model.new_place_samples is None:
            raise ModelError(f"parameter model_dir={model_dir!r}: the model has no Chow-Liu tree / new-place samples")
        self.vocabulary_id = model.vocabulary_id
        self.vocabulary_size = model.quantizer.size
        if self.robots and robot not in self.robots:  # a base station's own robot is its first: no empty session
            robot = self.robots[0]
        self.recognizer = PlaceRecognizer(
            ChowLiuTree.from_matrix(model.tree_matrix), model.new_place_samples, config, model.vocabulary_id, robot
        )
        warm_up_kernels()  # compile/load FAB-MAP's kernels now, not on the first image
        map_path = Path(map_file) if map_file else None
        if map_path is not None:
            for leftover in remove_stale_temporaries(map_path.parent, map_path.name):
                self.get_logger().warning(f"deleted {leftover}, left by a save that was killed")
        if map_path is not None and map_path.exists():
            differences = self.recognizer.load_map(map_path)
            session = self.recognizer.current_session
            self.get_logger().info(f"reloaded {self.recognizer.num_places} places in "
                                   f"{len(self.recognizer.sessions) - 1} session(s) from {map_path}; this run is "
                                   f"session {session.number} of robot {session.robot!r}")
            if differences:
                self.get_logger().warning(_differences_text(map_path, differences))
        # Frames at or before the robot's newest saved place are already in the map: replaying them after a
        # restart must not add them twice (they are answered, not recognised again).
        self.last_stamps_ns = ({name: self._ordering_stamp(map_path, name) for name in self.robots} if self.robots
                               else {robot: self._ordering_stamp(map_path, None)})
        self.counter = DropCounter(self)
        self.posterior_publisher = self.create_publisher(PlacePosterior, "place_posteriors", RESULT_QOS)
        self.loop_publisher = self.create_publisher(LoopClosure, "loop_closure_candidates", RESULT_QOS)
        self._subscribe_words(depth)
        self.map_saver = PeriodicSave(self, map_path, self.recognizer.save_map, "map", save_period_s)
        self.runtime_parameters = RuntimeParameters(self, RUNTIME_SETTINGS, self.recognizer.reconfigure)
        self.create_service(Trigger, "~/start_session", self._on_start_session)
        self.create_subscription(String, "~/start_robot_session", self._on_start_robot_session, 10)
        self.get_logger().info(
            f"FAB-MAP 2 on vocabulary {self.vocabulary_id} ({self.vocabulary_size} words), "
            f"match threshold {config.match_threshold}, {self.recognizer.num_places} places"
        )

    def _subscribe_words(self, depth: int) -> None:
        """aefabmap/words of the one robot; with ``robots``, each robot's /<robot>/aefabmap/words."""
        if not self.robots:
            words = counted_subscription(self, BagOfWords, "aefabmap/words", self._on_words, pipeline_qos(depth),
                                         self.counter)
            report_when_connected(self, words, "words")
        for name in self.robots:
            words = counted_subscription(self, BagOfWords, robot_topic(name, "aefabmap/words"),
                                         partial(self._on_words, robot=name), pipeline_qos(depth), self.counter)
            report_when_connected(self, words, f"words of {name}")

    @property
    def last_stamp_ns(self) -> int:
        """The stamp the next frame of this node's own robot must follow (-1 before any)."""
        return self.last_stamps_ns.get(self.recognizer.robot, -1)

    def _ordering_stamp(self, map_path: Path | None, robot: str | None) -> int:
        """The stamp ``robot``'s later frames must follow (None: the one robot's, every place is its): its newest
        place's, except places stamped in the future.

        Such places come from maps saved before future stamps were refused; they stay in the map (they
        are real images) but do not order later frames, or every frame would be dropped after every restart.
        """
        stamps = self.recognizer.place_stamps_ns
        if robot is not None and len(stamps):  # several robots: each robot's own places order its frames
            robot_sessions = np.array([session.robot == robot for session in self.recognizer.sessions])
            stamps = np.where(robot_sessions[self.recognizer.place_sessions], stamps, -1)
        newest, beyond = newest_stamp_up_to(stamps, self.future_stamps.limit_ns())
        if beyond:
            named = ", ".join(f"place {i} at {stamps[i] / 1e9:.0f} s" for i in beyond[:5])
            more = f" and {len(beyond) - 5} more" if len(beyond) > 5 else ""
            self.get_logger().warning(
                f"map {map_path} holds {len(beyond)} place(s) stamped more than max_future_stamp_s "
                f"{self.future_stamps.max_future_ns / 1e9:g} s ahead of the node's clock ({named}{more}); they are "
                f"kept but ignored for ordering: frames after {newest / 1e9:.3f} s are processed")
        return newest

    def _on_start_session(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """A new session from the next frame on (the robot was relocated; its odometry restarted)."""
        session = self.recognizer.start_session()
        self.map_saver.mark_changed()
        response.success = True
        response.message = f"session {session.number} of robot {session.robot!r} starts with the next frame"
        self.get_logger().info(response.message)
        return response

    @node_callback
    def _on_start_robot_session(self, message: String) -> None:
        """A new session of the robot named from its next frame on (one of ``robots``, or ``robot``)."""
        robot = message.data
        if robot not in (self.robots or [self.recognizer.robot]):
            self.counter.drop("unknown_robot", f"~/start_robot_session for robot {robot!r}, not one of this node's "
                              f"robots {self.robots or [self.recognizer.robot]}")
            return
        session = self.recognizer.start_session(robot)
        self.map_saver.mark_changed()
        self.get_logger().info(f"session {session.number} of robot {robot!r} starts with its next frame")

    @node_callback
    def _on_words(self, message: BagOfWords, robot: str | None = None) -> None:
        """Recognise one frame (of ``robot``, several robots; else of ``robot`` the parameter); every frame is
        answered on place_posteriors exactly once, a dropped one too (``query_id`` -1), so a lockstep replay never
        waits its timeout on a frame that reached us."""
        robot = self.recognizer.robot if robot is None else robot
        recognition = None
        try:
            recognition = self._recognise(message, robot)
        finally:  # an unexpected exception (counted by node_callback) gets its answer as well
            answer = (unrecognised_posterior(message.header, self.recognizer.num_places,
                                             self.recognizer.session_of(robot))
                      if recognition is None else recognition_to_posterior(recognition, message.header))
            answer.robot = robot
            self.posterior_publisher.publish(answer)
        if recognition is not None:
            self._publish_candidate(recognition, message.header)

    def _recognise(self, message: BagOfWords, robot: str) -> Recognition | None:
        """The frame recognised (and added to the map when it makes a place); None when it was dropped."""
        problem = header_stamp_problem(message.header, "BagOfWords")
        if problem is not None:
            self.counter.drop("bad_stamp", problem)
            return None
        stamp_ns = stamp_to_ns(message.header.stamp)
        last_ns = self.last_stamps_ns[robot]
        if stamp_ns <= last_ns:
            # After a restart, a replay's frames up to the newest saved place are already mapped.
            self.counter.drop("out_of_order", f"stamp {stamp_ns} ns of robot {robot!r} is not after its last one, "
                              f"{last_ns} ns (already mapped, or sent out of order)")
            return None
        problem = self.future_stamps.problem(stamp_ns)
        if problem is not None:
            self.counter.drop("stamp_in_future", problem)
            return None
        try:
            word_ids = message_to_word_ids(message, self.vocabulary_id, self.vocabulary_size)
            recognition = self.recognizer.process(word_ids, stamp_ns, robot=robot)
        except AefabmapError as exc:
            self.counter.drop(type(exc).__name__, str(exc))
            return None
        self.last_stamps_ns[robot] = stamp_ns
        if recognition.informative:  # the map (places, query count, belief) changed: save it
            self.map_saver.mark_changed()
        return recognition

    def _publish_candidate(self, recognition: Recognition, header: Any) -> None:
        """After the frame's posterior: count it, and publish its loop closure candidate if it has one."""
        if not recognition.informative:  # too few words to say anything: no place, no match
            self.counter.ok("frames_below_min_words")
            return
        loop_closure = recognition_to_loop_closure(recognition, header)
        if loop_closure is not None:
            self.loop_publisher.publish(loop_closure)
            self.counter.ok("loop_closure_candidates")
            self.get_logger().info(
                f"loop closure candidate: query {recognition.query_id} -> place {loop_closure.matched_place_id} "
                f"(p={loop_closure.probability:.4f})"
            )
        self.counter.ok()

    def close(self) -> bool:
        """The final map save; False when it failed (the process then exits 1)."""
        saved = self.map_saver.final_save()
        self.get_logger().info(f"fabmap_node: {self.recognizer.num_places} places"
                               f"{'' if saved else ' (NOT all saved)'}; {self.counter.summary()}")
        return saved


def _differences_text(map_path: Path, differences: ConfigDifferences) -> str:
    changes = ", ".join(f"{key} {saved!r} -> {now!r}" for key, (saved, now) in differences.items())
    return (f"map {map_path} was made with other FAB-MAP settings ({changes}); its places are used as they are, "
            "the current settings apply from now on")


def main(args: list[str] | None = None) -> int:
    return run_node(FabMapNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
