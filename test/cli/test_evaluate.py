"""aefabmap_eval: the four methods on a tiny synthetic sequence, --model, --train-on-test, recordings and
every bad input (ERROR: ..., exit 1)."""

import csv
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aefabmap_ros.cli import synth
from aefabmap_ros.cli.evaluate import main
from aefabmap_ros.evaluation.metrics import evaluate_scores, event_scores
from aefabmap_ros.verification.geometric import VerificationConfig
from test.evaluation.test_closure_scores import _three_event_gt

FRAMES = 30
# Tiny vocabularies so the whole module trains in seconds; names as in VocabularyConfig/FeatureConfig.
TINY_CONFIG = """\
feature:
  max_features: 120
vocabulary:
  size: 40
  num_threads: 1
  kmeans_iterations: 5
  ae_epochs: 1
  ae_max_train_descriptors: 1500
"""


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Quantizing with the autoencoder on one thread: far faster on a busy 2-core machine."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    args = ["--out", str(root / "synth"), "--kind", "both", "--frames", str(FRAMES), "--width", "160",
            "--height", "120", "--format", "both"]
    assert synth.main(args) == 0
    config = root / "tiny.yaml"
    config.write_text(TINY_CONFIG)
    return root


def paths(data):
    return data / "synth" / "test", data / "synth" / "train", data / "tiny.yaml"


def read_results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


def check_outputs(out: Path, methods: list[str]) -> dict:
    results = read_results(out)
    assert [m["method"] for m in results["methods"]] == methods
    for entry in results["methods"]:
        for key in ("average_precision", "max_f1", "recall_at_100_precision", "recall_at_threshold"):
            assert 0.0 <= entry[key] <= 1.0, (entry["method"], key)
        assert entry["accuracy_at_threshold"] is None or 0.0 <= entry["accuracy_at_threshold"] <= 1.0
        curve = entry["pr_curve"]
        assert all(0 <= v <= 1 for v in curve["precision"] + curve["recall"])
        assert (out / entry["scores_plot"]).stat().st_size > 1000
        fabmap = "FABMAP" in entry["method"] and not entry["geometric_verification"]
        assert (entry["reliability"] is not None) == fabmap and (entry["online_chain"] is not None) == fabmap
        if fabmap:
            # The nodes' posterior has no hypothesis within 5 s: the 3-s fixture bins none of its frames
            # (test/evaluation/test_online_chain.py checks what is binned on a longer sequence).
            assert sum(entry["reliability"]["counts"]) == 0
            online = entry["online_chain"]
            assert online["published"]["closures"] <= online["candidates"]["closures"]
            for topic in ("candidates", "published"):  # the decision's misses are among the missed frames
                missed = online[topic]["revisiting_frames"] - online[topic]["revisiting_frames_closed"]
                assert 0 <= online[topic]["missed_revisiting_frames_with_a_true_place_ranked"] <= missed
            assert 0 < online["places"] <= FRAMES
    assert (out / "pr_curves.png").read_bytes()[:4] == b"\x89PNG"
    if any("FABMAP" in m["method"] for m in results["methods"]):
        assert (out / "reliability.png").read_bytes()[:4] == b"\x89PNG"
        assert "Online chain" in (out / "results.md").read_text()
    table = (out / "results.md").read_text()
    for method in methods:
        assert f"| {method} |" in table
    assert results["frames"] == FRAMES and results["min_gap"] == 10
    return results


@pytest.fixture(scope="module")
def trained(data):
    """One evaluation with vocabularies trained on the separate training sequence (shared by tests)."""
    test, train, config = paths(data)
    out = data / "separate"
    # The 3-s fixture has no revisit 5 s apart (the covisibility loop_gt.npz is empty): score the pose rule.
    code = main(["--images", str(test / "images"), "--gt", str(test / "loop_gt_poses.npz"),
                 "--train-images", str(train / "images"), "--config", str(config), "--seed", "3",
                 "--out", str(out), "--quiet"])
    assert code == 0
    return out


def test_separate_training_writes_table_and_plots(trained, capsys):
    results = check_outputs(trained, ["FABMAP2", "AE-FABMAP", "BoW", "AE-BoW"])
    kinds = {m["method"]: (m["vocabulary_kind"], m["vocabulary_size"], m["model_id"]) for m in results["methods"]}
    assert kinds["FABMAP2"][:2] == ("kmeans", 40) and kinds["AE-FABMAP"][:2] == ("autoencoder", 40)
    assert kinds["FABMAP2"][2] == kinds["BoW"][2]  # one vocabulary per kind, shared by both its methods
    assert kinds["AE-FABMAP"][2] == kinds["AE-BoW"][2] != kinds["FABMAP2"][2]
    assert "train/images" in results["training"]
    assert {m["threshold"] for m in results["methods"]} == {0.99, 0.6}


def test_models_reused_give_the_same_numbers(data, trained, capsys):
    """--model on the models the first run trained: the same metrics (deterministic scoring)."""
    test, _, _ = paths(data)
    first = read_results(trained)
    models = sorted({m["model_path"] for m in first["methods"]})
    out = data / "reused"
    argv = ["--images", str(test / "images"), "--gt", str(test / "loop_gt_poses.npz"), "--out", str(out), "--quiet",
            "--methods", "ae-fabmap,fabmap2,bow"]
    for model in models:
        argv += ["--model", model]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "| FABMAP2 |" in printed and "results.md" in printed and "| AE-BoW |" not in printed
    again = check_outputs(out, ["FABMAP2", "AE-FABMAP", "BoW"])
    before = {m["method"]: m for m in first["methods"]}
    for entry in again["methods"]:
        for key in ("average_precision", "max_f1", "recall_at_100_precision", "pr_curve"):
            assert entry[key] == before[entry["method"]][key]


def test_verify_adds_a_geometrically_verified_row_per_method(data, trained, capsys):
    """--verify: each method also scored after verification; its rows keep at most one candidate per
    query, never above the unverified score, so precision can only be traded for recall."""
    test, _, _ = paths(data)
    first = read_results(trained)
    out = data / "verified"
    argv = ["--images", str(test / "images"), "--gt", str(test / "loop_gt_poses.npz"), "--out", str(out), "--quiet",
            "--verify", "--methods", "ae-fabmap,bow"]
    for model in sorted({m["model_path"] for m in first["methods"]}):
        argv += ["--model", model]
    assert main(argv) == 0
    assert "| AE-FABMAP + GV |" in capsys.readouterr().out
    results = check_outputs(out, ["AE-FABMAP", "AE-FABMAP", "BoW", "BoW"])
    flags = [(m["method"], m["geometric_verification"]) for m in results["methods"]]
    assert flags == [("AE-FABMAP", False), ("AE-FABMAP", True), ("BoW", False), ("BoW", True)]
    assert results["geometric_verification"]["min_inliers"] == VerificationConfig().min_inliers
    plain, verified = results["methods"][0], results["methods"][1]
    assert plain["recall_at_threshold"] == first["methods"][1]["recall_at_threshold"]
    assert verified["num_predictions_at_threshold"] <= plain["num_predictions_at_threshold"]
    assert verified["scores_plot"] != plain["scores_plot"]
    assert plain["online_chain"]["verified"] and not first["methods"][1]["online_chain"]["verified"]


def test_verify_with_depth_gives_the_metric_test_from_a_folder_or_the_bag_alike(data, trained, capsys):
    """--depth/--camera-info (folder) and --depth-topic/--camera-info-topic (bag) bring the same depth, so the
    verified rows agree; the metric test only adds accepted pairs, so no query loses its verified candidate."""
    test, _, _ = paths(data)
    models = sorted({m["model_path"] for m in read_results(trained)["methods"]})
    common = ["--gt", str(test / "loop_gt_poses.npz"), "--quiet", "--verify", "--methods", "ae-fabmap,bow"]
    for model in models:
        common += ["--model", model]
    runs = {
        "plain": ["--images", str(test / "images")],
        "folder": ["--images", str(test / "images"), "--depth", str(test / "depth"),
                   "--camera-info", str(test / "camera_info.yaml")],
        "bag": ["--bag", str(test / "bag"), "--depth-topic", "/depth", "--camera-info-topic", "/camera_info"],
    }
    verified = {}
    for name, argv in runs.items():
        assert main(argv + common + ["--out", str(data / f"depth-{name}")]) == 0
        results = read_results(data / f"depth-{name}")
        assert ("metric test" in results["depth"]) == (name != "plain")
        verified[name] = [m for m in results["methods"] if m["geometric_verification"]]
    for folder, bag in zip(verified["folder"], verified["bag"], strict=True):
        assert folder["average_precision"] == bag["average_precision"] and folder["pr_curve"] == bag["pr_curve"]
    for plain, depth in zip(verified["plain"], verified["folder"], strict=True):
        assert depth["num_queries"] >= plain["num_queries"]


@pytest.mark.parametrize(("extra", "message"), [
    (["--depth", "D"], "the intrinsics"),
    (["--camera-info", "C"], "give --depth"),
    (["--depth-topic", "/depth", "--camera-info-topic", "/camera_info"], "is a topic of --bag"),
])
def test_error_depth_options_that_do_not_fit(data, trained, capsys, extra, message):
    test, _, _ = paths(data)
    models = sorted({m["model_path"] for m in read_results(trained)["methods"]})
    argv = ["--images", str(test / "images"), "--gt", str(test / "loop_gt_poses.npz"), "--verify", "--quiet",
            "--out", str(data / "depth-error"), "--model", models[0], *extra]
    assert message in run_error(argv, capsys)
    no_verify = ["--images", str(test / "images"), "--gt", str(test / "loop_gt_poses.npz"), "--quiet",
                 "--out", str(data / "depth-error"), "--model", models[0], "--depth", str(test / "depth"),
                 "--camera-info", str(test / "camera_info.yaml")]
    assert "add --verify" in run_error(no_verify, capsys)


@pytest.mark.parametrize("extra", [["--verify"], ["--depth-topic", "/depth"], ["--camera-info", "camera_info.yaml"]])
def test_error_verify_or_depth_with_a_recording(data, capsys, extra):
    test, _, _ = paths(data)
    code = main(["--recording", str(test), "--gt", str(test / "loop_gt.npz"), *extra, "--out", str(data / "bad")])
    assert code == 1 and "no images, depth, models or --verify" in capsys.readouterr().err


def test_train_on_test_from_a_bag_with_poses(data):
    test, _, config = paths(data)
    out = data / "on_test"
    code = main(["--bag", str(test / "bag"), "--topic", "/image", "--poses", str(test / "poses.txt"),
                 "--max-distance", "2.5", "--max-angle", "30", "--train-on-test", "--config", str(config),
                 "--methods", "FABMAP2,BoW", "--bow-threshold", "0.5", "--out", str(out), "--quiet"])
    assert code == 0
    results = check_outputs(out, ["FABMAP2", "BoW"])
    assert "train-on-test" in results["training"]
    assert results["methods"][1]["threshold"] == 0.5
    # The pose rule with the generator's parameters reproduces its pose-rule loop matrix (loop_gt.npz is
    # covisibility now: the 3 s of this 30-frame fixture hold no revisit 5 s apart).
    with np.load(test / "loop_gt_poses.npz") as gt:
        positive = int(np.tril(gt["gt"], -10).any(axis=1).sum())
    assert results["positive_queries"] == positive > 0


# ------------------------------------------------------------------------------------------ bad inputs


def run_error(argv, capsys) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: "), err
    return err


@pytest.fixture
def base(data, tmp_path):
    test, train, _ = paths(data)
    return {"test": test, "train": train, "out": tmp_path / "out"}


def test_error_gt_of_the_wrong_size(base, tmp_path, capsys):
    np.savez(tmp_path / "gt.npz", gt=np.zeros((FRAMES - 1, FRAMES - 1), np.uint8))
    err = run_error(["--images", str(base["test"] / "images"), "--gt", str(tmp_path / "gt.npz"),
                     "--train-on-test", "--out", str(base["out"])], capsys)
    assert f"ground truth is {FRAMES - 1}x{FRAMES - 1}" in err and f"has {FRAMES} frames" in err


def test_error_missing_topic(base, capsys):
    err = run_error(["--bag", str(base["test"] / "bag"), "--topic", "/camera/nope", "--gt",
                     str(base["test"] / "loop_gt.npz"), "--train-on-test", "--out", str(base["out"])], capsys)
    assert "'/camera/nope' not in bag" in err and "/image" in err


def test_error_empty_folder(base, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    err = run_error(["--images", str(tmp_path / "empty"), "--gt", str(base["test"] / "loop_gt.npz"),
                     "--train-on-test", "--out", str(base["out"])], capsys)
    assert "no image files" in err


@pytest.mark.parametrize("missing", ["gt", "images", "train-images", "model", "config", "recording", "poses"])
def test_error_missing_files(base, tmp_path, capsys, missing):
    nowhere = str(tmp_path / "does_not_exist")
    argv = {
        "gt": ["--images", str(base["test"] / "images"), "--gt", nowhere, "--train-on-test"],
        "images": ["--images", nowhere, "--gt", str(base["test"] / "loop_gt.npz"), "--train-on-test"],
        "train-images": ["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                         "--train-images", nowhere],
        "model": ["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                  "--model", nowhere],
        "config": ["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                   "--train-on-test", "--config", nowhere],
        "recording": ["--recording", nowhere, "--gt", str(base["test"] / "loop_gt.npz")],
        "poses": ["--images", str(base["test"] / "images"), "--poses", nowhere, "--max-distance", "2",
                  "--max-angle", "30", "--train-on-test"],
    }[missing]
    err = run_error([*argv, "--out", str(base["out"])], capsys)
    assert "does_not_exist" in err


def test_error_unknown_method(base, capsys):
    err = run_error(["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                     "--train-on-test", "--methods", "FABMAP2,NetVLAD", "--out", str(base["out"])], capsys)
    assert "unknown method 'NetVLAD'" in err and "AE-FABMAP" in err


def test_error_unwritable_output(base, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    err = run_error(["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                     "--train-on-test", "--out", str(blocker / "results")], capsys)
    assert "is not a writable folder" in err


@pytest.mark.parametrize(("extra", "message"), [
    ([], "exactly one of: --train-images/--train-bag, --train-on-test, --model"),
    (["--train-on-test", "--model", "m"], "exactly one of"),
    (["--train-on-test", "--threshold", "1.5"], "threshold=1.5"),
    (["--train-on-test", "--bogus"], "unrecognized arguments: --bogus"),
])
def test_error_bad_choices(base, capsys, extra, message):
    err = run_error(["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                     "--out", str(base["out"]), *extra], capsys)
    assert message in err


def test_error_poses_without_rule(base, capsys):
    err = run_error(["--images", str(base["test"] / "images"), "--poses", str(base["test"] / "poses.txt"),
                     "--train-on-test", "--out", str(base["out"])], capsys)
    assert "--poses needs --max-distance" in err


def test_error_unknown_config_key(base, tmp_path, capsys):
    config = tmp_path / "bad.yaml"
    config.write_text("evaluation:\n  min_gapp: 3\n")
    err = run_error(["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                     "--train-on-test", "--config", str(config), "--out", str(base["out"])], capsys)
    assert "min_gapp" in err


# ------------------------------------------------------------------------------------------ recordings


START = 1_700_000_000_000_000_000
PERIOD = 100_000_000


def frame_stamp(frame: int) -> int:
    return START + frame * PERIOD


# query frame, matched frame, probability[, inliers[, T_q_m 4x4, metric]]
RecordedClosure = tuple[Any, ...]


def write_recording(path: Path, posteriors: list[tuple[int, list[int], list[float]]],
                    closures: Mapping[str, Sequence[RecordedClosure]], query_ids: Mapping[int, int] | None = None,
                    posterior_topic: str = "/place_posteriors",
                    sessions: Mapping[int, tuple[str, int]] | None = None) -> None:
    """A recording with ``posterior_topic`` and one LoopClosure topic per key of ``closures``. Entries name
    frames (stamped ``frame_stamp``); ``query_ids`` numbers them as fabmap_node did (default: the frame);
    ``sessions`` gives a frame's (robot, session) (default: ('', 0), a map of one session)."""
    from aefabmap_ros.io import bag_messages, bags

    types = bag_messages.get_typestore().types
    ids = query_ids or {}

    def session(frame: int) -> tuple[str, int]:
        return (sessions or {}).get(frame, ("", 0))

    with bags.BagWriter(path) as writer:
        writer.add_topic(posterior_topic, "aefabmap_msgs/msg/PlacePosterior")
        for topic in closures:
            writer.add_topic(topic, "aefabmap_msgs/msg/LoopClosure")
        for frame, places, probabilities in posteriors:
            query = ids.get(frame, frame)
            message = types["aefabmap_msgs/msg/PlacePosterior"](
                header=bag_messages.make_header(frame_stamp(frame)), query_id=query, assigned_place_id=query,
                current_place_id=query,
                is_new_place=True, loop_closure_candidate=False, new_place_probability=1.0 - sum(probabilities),
                place_ids=np.array([ids.get(p, p) for p in places], dtype=np.int64),
                place_stamps=[bag_messages.make_time(frame_stamp(p)) for p in places],
                probabilities=np.array(probabilities, dtype=np.float64),
                log_likelihoods=np.zeros(len(places), dtype=np.float64),
                robot=session(frame)[0], session=session(frame)[1],
                place_sessions=np.array([session(p)[1] for p in places], dtype=np.uint32),
                place_robots=[session(p)[0] for p in places],
            )
            writer.write(posterior_topic, frame_stamp(frame), message)
        for topic, entries in closures.items():
            for frame, place, probability, *rest in entries:
                pose = bag_messages.no_pose_fields()
                if len(rest) > 1:
                    matrix, metric = rest[1], rest[2]
                    x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
                    pose.update(pose_available=True, pose_status=0, translation_metric=metric,
                                pose=types["geometry_msgs/msg/Pose"](
                                    position=types["geometry_msgs/msg/Point"](*(float(v) for v in matrix[:3, 3])),
                                    orientation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)))
                message = types["aefabmap_msgs/msg/LoopClosure"](
                    header=bag_messages.make_header(frame_stamp(frame)), query_id=ids.get(frame, frame),
                    query_place_id=ids.get(place, place), matched_place_id=ids.get(place, place),
                    matched_stamp=bag_messages.make_time(frame_stamp(place)), probability=probability,
                    log_likelihood=0.0,
                    inliers=rest[0] if rest else -1, **pose,
                    query_robot=session(frame)[0], query_session=session(frame)[1],
                    matched_robot=session(place)[0], matched_session=session(place)[1],
                )
                writer.write(topic, frame_stamp(frame), message)


def save_gt(path: Path, gt: np.ndarray, stamps: bool = True) -> None:
    """A ground-truth .npz; with its rows' stamps (``frame_stamp``), as aefabmap_gt and aefabmap_synth write it."""
    if stamps:
        np.savez(path, gt=gt, stamps_ns=np.array([frame_stamp(i) for i in range(gt.shape[0])], dtype=np.int64))
    else:
        np.savez(path, gt=gt)


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open() as file:
        return list(csv.DictReader(file))


def test_recording_metrics(tmp_path, capsys):
    frames = 20
    gt = np.zeros((frames, frames), np.uint8)
    for i in range(12, 20):
        gt[i, i - 12] = 1  # frames 12..19 revisit 0..7: one revisit event of 8 frames
    posteriors = []
    expected = np.zeros((frames, frames))
    rng = np.random.default_rng(5)
    for i in range(frames):
        places = list(range(i))[-5:]  # top-5 of the recording: mostly recent frames
        probabilities = list(rng.uniform(0.0, 0.1, len(places)))
        if i >= 12:
            places.append(i - 12)
            probabilities.append([0.999, 0.995, 0.2, 0.97, 0.999, 0.5, 0.3, 0.9][i - 12])
        if i == 15:  # a confident wrong candidate beats the true one
            places.append(1)
            probabilities.append(0.98)
        expected[i, places] = probabilities
        posteriors.append((i, places, probabilities))
    candidates = [(12, 0, 0.999), (16, 4, 0.999), (18, 2, 0.9995)]  # the last one is wrong
    expected[18, 2] = 0.9995
    published = [(12, 0, 0.999, 57)]  # the verifier passed one true closure and held back the other two
    write_recording(tmp_path / "run", posteriors, {"/loop_closure_candidates": candidates,
                                                   "/loop_closures": published})
    save_gt(tmp_path / "gt.npz", gt)
    assert main(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"), "--threshold", "0.99",
                 "--out", str(tmp_path / "out"), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "| recording |" in printed
    results = read_results(tmp_path / "out")
    reference = evaluate_scores(expected, gt, 10, 0.99)
    entry = results["methods"][0]
    assert entry["average_precision"] == pytest.approx(reference.average_precision)
    assert entry["recall_at_100_precision"] == pytest.approx(reference.recall_at_100_precision)
    assert entry["pr_curve"]["precision"] == pytest.approx(reference.pr_precision.tolist())
    # By hand: best candidates 12:0.999 T, 13:0.995 T, 14:0.2 T, 15:0.98 F, 16:0.999 T, 17:0.5 T, 18:0.9995 F
    # (18 -> 2, the recorded closure), 19:0.9 T. At 0.99: predictions 18, 12, 16, 13 -> 3 of 4 true; recall 3 / 8.
    assert entry["accuracy_at_threshold"] == pytest.approx(0.75)
    assert entry["recall_at_threshold"] == pytest.approx(3 / 8)
    assert entry["recall_at_100_precision"] == 0.0  # the top-scoring proposal (18 -> 2) is wrong
    assert results["place_posteriors"] == results["frames_processed"] == frames and results["event_gap_frames"] == 3
    assert results["frame_stamps"].startswith(f"the stamps_ns of {tmp_path / 'gt.npz'} (20 stamped frames")
    raw, verified = results["closures"]
    # Candidates: 12 -> 0 and 16 -> 4 true, 18 -> 2 false; the one event (12..19) closed; frames 12, 16 of 8.
    assert raw == {"role": "FAB-MAP candidates", "topic": "loop_closure_candidates", "closures": 3, "verified": 0,
                   "false_closures": 1, "precision": pytest.approx(2 / 3), "revisit_events": 1, "events_closed": 1,
                   "fraction_of_events_closed": 1.0, "revisiting_frames": 8, "revisiting_frames_closed": 2,
                   "recall_revisiting_frames": 0.25, "revisiting_frames_processed": 8,
                   "revisiting_frames_processed_closed": 2, "recall_revisiting_frames_processed": 0.25,
                   "missed_revisiting_frames_with_a_true_place_ranked": 6, "wrong_poses": None, "poses_checked": None,
                   "poses_outside_covariance": None, "poses_covariance_checked": None}
    assert verified == {"role": "published", "topic": "loop_closures", "closures": 1, "verified": 1,
                        "false_closures": 0, "precision": 1.0, "revisit_events": 1, "events_closed": 1,
                        "fraction_of_events_closed": 1.0, "revisiting_frames": 8, "revisiting_frames_closed": 1,
                        "recall_revisiting_frames": 0.125, "revisiting_frames_processed": 8,
                        "revisiting_frames_processed_closed": 1, "recall_revisiting_frames_processed": 0.125,
                        "missed_revisiting_frames_with_a_true_place_ranked": 7, "wrong_poses": None,
                        "poses_checked": None, "poses_outside_covariance": None, "poses_covariance_checked": None}
    # Every revisiting frame had its true place among its recorded top places: each miss is the decision's.
    assert ("| published | `loop_closures` | 1 | 1 | 0 | 1.000 | 1 | 1 | 1.000 | 0.125 (1/8) | 0.125 (1/8) "
            "| 7 / 7 |") in printed
    row = ("| FAB-MAP candidates | `loop_closure_candidates` | 3 | 0 | 1 | 0.667 | 1 | 1 | 1.000 | 0.250 (2/8) "
           "| 0.250 (2/8) | 6 / 6 |")
    markdown = (tmp_path / "out" / "results.md").read_text()
    assert row in markdown
    assert ("| `loop_closure_candidates` | 18 | 1700000001.800000000 | 2 | 1700000000.200000000 | 0.9995 | -1 |  |  |"
            in markdown)  # the false closure, listed
    assert (tmp_path / "out" / "scores_recording.png").is_file()
    listing = read_csv(tmp_path / "out" / "closures.csv")
    assert [(r["topic"], r["query_frame"], r["matched_frame"], r["true"]) for r in listing] == [
        ("loop_closure_candidates", "12", "0", "1"), ("loop_closure_candidates", "16", "4", "1"),
        ("loop_closure_candidates", "18", "2", "0"), ("loop_closures", "12", "0", "1")]


def test_recording_events_and_an_older_recording(tmp_path, capsys):
    """An older recording (verified_loop_closures): its loop_closures are the candidates, its
    verified_loop_closures the published closures; both scored per revisit event, by hand."""
    save_gt(tmp_path / "gt.npz", _three_event_gt())
    raw = [(13, 1, 0.999), (17, 5, 0.995), (26, 6, 0.999), (30, 3, 0.999), (35, 21, 0.999)]  # last two false
    verified = [(13, 1, 0.999, 40), (26, 7, 0.999, 33)]  # 26 moved to 7, also a true revisit
    write_recording(tmp_path / "old", [(i, [], []) for i in range(40)],
                    {"/loop_closures": raw, "/verified_loop_closures": verified})
    assert main(["--recording", str(tmp_path / "old"), "--gt", str(tmp_path / "gt.npz"),
                 "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert "An older recording" in capsys.readouterr().out
    candidates, published = read_results(tmp_path / "out")["closures"]
    assert (candidates["role"], candidates["topic"], published["role"], published["topic"]) == (
        "FAB-MAP candidates", "loop_closures", "published", "verified_loop_closures")
    # Candidates: A closed (13, 17), B closed (26), C not (35 -> 21 is false); frames 13, 17, 26 of 10.
    assert (candidates["closures"], candidates["false_closures"], candidates["precision"]) == (5, 2, 0.6)
    assert (candidates["revisit_events"], candidates["events_closed"]) == (3, 2)
    assert (candidates["revisiting_frames"], candidates["revisiting_frames_closed"]) == (10, 3)
    # Published: A (13) and B (26) closed, nothing false; frames 13, 26.
    assert (published["closures"], published["verified"], published["false_closures"]) == (2, 2, 0)
    assert (published["events_closed"], published["fraction_of_events_closed"]) == (2, pytest.approx(2 / 3))
    assert published["recall_revisiting_frames"] == pytest.approx(0.2)
    # No posterior ranked anything: every missed frame is the ranking's.
    assert published["missed_revisiting_frames_with_a_true_place_ranked"] == 0

    # Verification off (aefabmap_launch --no-verify): only loop_closures, FAB-MAP's own, inliers -1.
    write_recording(tmp_path / "raw", [(i, [], []) for i in range(40)], {"/loop_closures": raw})
    assert main(["--recording", str(tmp_path / "raw"), "--gt", str(tmp_path / "gt.npz"),
                 "--out", str(tmp_path / "out_raw"), "--quiet"]) == 0
    (only,) = read_results(tmp_path / "out_raw")["closures"]
    assert (only["role"], only["closures"], only["verified"], only["events_closed"]) == ("published", 5, 0, 2)


# Frames that never reached fabmap_node (a live camera's losses, a detection-rate policy), and the closures
# of the frames that did, as (query frame, matched frame, probability, inliers): 15 -> 4 and 35 -> 21 are false.
LOST = (3, 9, 10, 14, 16, 22, 26, 33)
LOSSY_CLOSURES = [(12, 0, 0.999, 50), (13, 1, 0.99, 44), (15, 4, 0.98, 31), (17, 5, 0.999, 60), (25, 5, 0.97, 28),
                  (27, 8, 0.999, 35), (35, 21, 0.999, 30)]


def write_lossy_recording(path: Path, posterior_topic: str = "/place_posteriors") -> None:
    received = [frame for frame in range(40) if frame not in LOST]
    query_ids = {frame: index for index, frame in enumerate(received)}  # fabmap_node counts what it got
    write_recording(path, [(frame, [], []) for frame in received], {"/loop_closures": LOSSY_CLOSURES},
                    query_ids=query_ids, posterior_topic=posterior_topic)


def test_a_recording_with_lost_frames_is_scored_by_stamp(tmp_path, capsys):
    """Frames lost before fabmap_node renumber its query ids; by stamp, the closures land on their frames:
    the figures are those of the same closures given as frame pairs to the metrics."""
    gt = _three_event_gt()
    save_gt(tmp_path / "gt.npz", gt)
    write_lossy_recording(tmp_path / "run")
    assert main(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"),
                 "--out", str(tmp_path / "out"), "--quiet"]) == 0
    results = read_results(tmp_path / "out")
    (published,) = results["closures"]
    pairs = [(query, matched) for query, matched, *_ in LOSSY_CLOSURES]
    reference = event_scores(pairs, gt, 10)
    assert (published["closures"], published["false_closures"]) == (reference.num_closures,
                                                                     reference.num_false_closures) == (7, 2)
    assert (published["revisit_events"], published["events_closed"]) == (reference.num_events,
                                                                         reference.num_events_closed)
    assert (published["revisiting_frames"], published["revisiting_frames_closed"]) == (
        reference.num_revisiting_frames, reference.num_revisiting_frames_closed) == (10, 5)
    assert published["precision"] == pytest.approx(5 / 7)
    # Recall over the frames the detector processed: revisiting frames 14 and 26 never reached it.
    assert results["frames_processed"] == 40 - len(LOST)
    assert (published["revisiting_frames_processed"], published["revisiting_frames_processed_closed"]) == (8, 5)
    assert published["recall_revisiting_frames_processed"] == pytest.approx(5 / 8)
    listing = read_csv(tmp_path / "out" / "closures.csv")
    assert [(int(r["query_frame"]), int(r["matched_frame"])) for r in listing] == pairs
    assert [r["true"] for r in listing] == ["1", "1", "0", "1", "1", "1", "0"]
    assert [r["query_stamp"] for r in listing][:2] == ["1700000001.200000000", "1700000001.300000000"]
    assert [r["inliers"] for r in listing] == [str(entry[3]) for entry in LOSSY_CLOSURES]
    # Read by query id, the same recording puts the closures on other rows (right only for a lossless replay).
    assert main(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"), "--frames-by-query-id",
                 "--out", str(tmp_path / "by_id"), "--quiet"]) == 0
    (by_id,) = read_results(tmp_path / "by_id")["closures"]
    assert by_id["false_closures"] != published["false_closures"]


def test_frame_stamps_from_a_times_file_of_float_seconds_or_from_the_image_bag(tmp_path, capsys):
    """--times (seconds, as floats: some 100 ns off the recorded stamps, matched within 1 ms) and --bag
    (the images' header stamps) give the frames the gt file's stamps_ns gives."""
    from aefabmap_ros.io import bags

    gt = _three_event_gt()
    save_gt(tmp_path / "stamped.npz", gt)
    save_gt(tmp_path / "gt.npz", gt, stamps=False)
    write_lossy_recording(tmp_path / "run")
    (tmp_path / "times.txt").write_text("".join(f"{frame_stamp(i) / 1e9:.6f}\n" for i in range(40)))
    bags.write_image_bag(tmp_path / "images", "/cam", [(frame_stamp(i), np.zeros((4, 4), np.uint8))
                                                       for i in range(40)])
    figures = {}
    for name, extra in (("stamped", ["--gt", str(tmp_path / "stamped.npz")]),
                        ("times", ["--gt", str(tmp_path / "gt.npz"), "--times", str(tmp_path / "times.txt")]),
                        ("bag", ["--gt", str(tmp_path / "gt.npz"), "--bag", str(tmp_path / "images"),
                                 "--topic", "/cam"])):
        assert main(["--recording", str(tmp_path / "run"), *extra, "--out", str(tmp_path / name), "--quiet"]) == 0
        results = read_results(tmp_path / name)
        figures[name] = (results["closures"], read_csv(tmp_path / name / "closures.csv"))
        assert results["frames_processed"] == 32
    assert figures["times"] == figures["stamped"] == figures["bag"]
    assert "--times" in read_results(tmp_path / "times")["frame_stamps"]
    assert "within 1 ms" in read_results(tmp_path / "times")["frame_stamps"]
    assert "/cam images of" in read_results(tmp_path / "bag")["frame_stamps"]


def test_a_recording_without_frame_stamps_is_refused(tmp_path, capsys):
    save_gt(tmp_path / "gt.npz", _three_event_gt(), stamps=False)
    write_lossy_recording(tmp_path / "run")
    err = run_error(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"),
                     "--out", str(tmp_path / "out")], capsys)
    assert "matched to ground-truth frames by their image stamps, and no frame stamps were given" in err
    assert "--times FILE" in err and "--bag BAG --topic TOPIC" in err and "stamps_ns" in err
    assert not (tmp_path / "out").exists()


def test_a_recorded_stamp_that_is_no_frame_is_refused(tmp_path, capsys):
    gt = _three_event_gt()
    write_lossy_recording(tmp_path / "run")
    # A times file of seconds since the first frame (KITTI's, aefabmap_synth's): the recording's stamps are absolute.
    save_gt(tmp_path / "gt.npz", gt, stamps=False)
    (tmp_path / "times.txt").write_text("".join(f"{i / 10:.6f}\n" for i in range(40)))
    err = run_error(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"),
                     "--times", str(tmp_path / "times.txt"), "--out", str(tmp_path / "out")], capsys)
    assert "32 recorded stamps match no frame of --times" in err  # the posteriors: the score matrix's first
    assert "the first: place_posteriors query stamped 1700000000.000000000 s" in err
    assert "seconds since the first frame" in err
    # One frame of the gt's stamps differs from the recording's: its stamp matches no frame.
    stamps = np.array([frame_stamp(i) for i in range(40)], dtype=np.int64)
    stamps[5] += 1
    np.savez(tmp_path / "off.npz", gt=gt, stamps_ns=stamps)
    err = run_error(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "off.npz"),
                     "--out", str(tmp_path / "out")], capsys)
    assert "1 recorded stamp matches no frame" in err
    assert "place_posteriors query stamped 1700000000.500000000 s" in err
    # Frame 5 is only a closure's matched place when its posterior is not recorded: refused all the same.
    received = [frame for frame in range(40) if frame not in (*LOST, 5)]
    write_recording(tmp_path / "run5", [(frame, [], []) for frame in received], {"/loop_closures": LOSSY_CLOSURES})
    err = run_error(["--recording", str(tmp_path / "run5"), "--gt", str(tmp_path / "off.npz"),
                     "--out", str(tmp_path / "out")], capsys)
    assert "2 recorded stamps match no frame" in err  # 17 -> 5 and 25 -> 5
    assert "loop closure matched place stamped 1700000000.500000000 s" in err


@pytest.mark.parametrize(("extra", "message"), [
    (["--times", "t.txt", "--bag", "b"], "--times FILE or --bag BAG, not both"),
    (["--frames-by-query-id", "--times", "t.txt"], "give no --times or --bag with it"),
])
def test_recording_frame_options_that_do_not_fit(tmp_path, capsys, extra, message):
    save_gt(tmp_path / "gt.npz", _three_event_gt())
    write_lossy_recording(tmp_path / "run")
    err = run_error(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"), *extra,
                     "--out", str(tmp_path / "out")], capsys)
    assert message in err


@pytest.mark.parametrize("extra", [["--times", "t.txt"], ["--pose-truth", "p.tum"], ["--frames-by-query-id"]])
def test_recording_options_without_a_recording(base, capsys, extra):
    err = run_error(["--images", str(base["test"] / "images"), "--gt", str(base["test"] / "loop_gt.npz"),
                     "--train-on-test", *extra, "--out", str(base["out"])], capsys)
    assert "go with --recording" in err


def test_recording_topics_with_and_without_a_leading_slash(tmp_path, capsys):
    """aefabmap_record stores the names it subscribed to (place_posteriors), ros2 bag record absolute ones."""
    save_gt(tmp_path / "gt.npz", _three_event_gt())
    write_lossy_recording(tmp_path / "relative", posterior_topic="place_posteriors")
    assert main(["--recording", str(tmp_path / "relative"), "--gt", str(tmp_path / "gt.npz"),
                 "--out", str(tmp_path / "out"), "--quiet"]) == 0
    results = read_results(tmp_path / "out")
    assert results["frames_processed"] == 32 and results["closures"][0]["closures"] == 7
    write_recording(tmp_path / "twice", [(1, [], [])], {"/loop_closures": [], "loop_closures": []})
    err = run_error(["--recording", str(tmp_path / "twice"), "--gt", str(tmp_path / "gt.npz"),
                     "--out", str(tmp_path / "out2")], capsys)
    assert "has both '/loop_closures' and 'loop_closures': one topic recorded twice" in err


def test_recording_with_a_pose_truth(tmp_path, capsys):
    """--pose-truth: each closure's relative pose (T_q_m) against the TUM poses at its two stamps."""
    from aefabmap_ros.evaluation.trajectory_error import tum_text

    gt = _three_event_gt()
    save_gt(tmp_path / "gt.npz", gt)
    poses = np.tile(np.eye(4), (40, 1, 1))
    poses[:, 0, 3] = np.arange(40) * 0.1  # the camera moves along its x axis, 0.1 m a frame, never turning
    (tmp_path / "groundtruth.tum").write_text(tum_text(np.array([frame_stamp(i) for i in range(40)]) / 1e9, poses))
    right = np.eye(4)
    right[0, 3] = -1.2  # frame 0 seen from frame 12: 1.2 m along -x
    wrong = np.eye(4)
    wrong[:3, :3] = Rotation.from_euler("y", 10, degrees=True).as_matrix()
    wrong[0, 3] = -1.2 - 0.3
    closures = [(12, 0, 0.999, 50, right, True), (13, 1, 0.99, 44, wrong, True), (17, 5, 0.999, 60)]
    write_recording(tmp_path / "run", [(i, [], []) for i in range(40)], {"/loop_closures": closures})
    assert main(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"), "--pose-truth",
                 str(tmp_path / "groundtruth.tum"), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "wrong poses (> 5 deg or > 0.2 m) / checked |" in printed and printed.count("| 1 / 2 |") == 1
    (published,) = read_results(tmp_path / "out")["closures"]
    assert (published["wrong_poses"], published["poses_checked"]) == (1, 2)
    first, second, third = read_csv(tmp_path / "out" / "closures.csv")
    assert float(first["rotation_error_deg"]) == pytest.approx(0.0, abs=1e-4) and first["pose_wrong"] == "0"
    assert float(first["translation_error_m"]) == pytest.approx(0.0, abs=1e-5)
    assert float(second["rotation_error_deg"]) == pytest.approx(10.0, abs=1e-4) and second["pose_wrong"] == "1"
    assert float(second["translation_error_m"]) == pytest.approx(0.3, abs=1e-5)
    assert third["pose_available"] == "0" and third["rotation_error_deg"] == ""
    assert "Closures with a wrong relative pose" in (tmp_path / "out" / "results.md").read_text()


def test_recording_of_two_layouts_at_once_is_refused(tmp_path, capsys):
    save_gt(tmp_path / "gt.npz", _three_event_gt())
    write_recording(tmp_path / "mixed", [(13, [], [])], {"/loop_closure_candidates": [(13, 1, 0.999)],
                                                         "/verified_loop_closures": [(13, 1, 0.999, 40)]})
    err = run_error(["--recording", str(tmp_path / "mixed"), "--gt", str(tmp_path / "gt.npz"),
                     "--out", str(tmp_path / "out")], capsys)
    assert "has both verified_loop_closures" in err and "loop_closure_candidates" in err


def test_recording_without_the_topics(tmp_path, capsys):
    from aefabmap_ros.io import bags

    bags.write_image_bag(tmp_path / "images", "/image", [(1, np.zeros((4, 4), np.uint8))])
    save_gt(tmp_path / "gt.npz", np.zeros((3, 3), np.uint8))
    err = run_error(["--recording", str(tmp_path / "images"), "--gt", str(tmp_path / "gt.npz"),
                     "--out", str(tmp_path / "out")], capsys)
    assert "has none of place_posteriors, loop_closures, loop_closure_candidates" in err


def test_recording_by_query_id_with_a_query_beyond_the_ground_truth(tmp_path, capsys):
    write_recording(tmp_path / "run", [(0, [], []), (5, [0], [0.5])], {})
    save_gt(tmp_path / "gt.npz", np.zeros((3, 3), np.uint8), stamps=False)
    err = run_error(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"), "--frames-by-query-id",
                     "--out", str(tmp_path / "out")], capsys)
    assert "query id 5 outside the 3 frames" in err


@pytest.mark.parametrize("extra", [[], ["--work-dir", "cache/deep"]])
def test_a_refused_evaluation_leaves_no_out_folder_and_no_empty_cache(tmp_path: Path, extra: list[str],
                                                                       capsys: pytest.CaptureFixture[str],
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The vocabulary source is validated only once the output and cache folders exist; refused, it removes them."""
    monkeypatch.chdir(tmp_path)
    gt = tmp_path / "gt.npz"
    np.savez(gt, gt=np.zeros((3, 3), bool))
    images = tmp_path / "images"
    images.mkdir()
    assert main(["--images", str(images), "--gt", str(gt), "--out", "OUT", "--quiet", *extra]) == 1
    assert capsys.readouterr().err.startswith("ERROR: ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gt.npz", "images"]


def test_a_refused_evaluation_keeps_an_out_folder_that_existed(tmp_path: Path) -> None:
    out = tmp_path / "OUT"
    out.mkdir()
    (out / "results.md").write_text("an earlier run")
    assert main(["--gt", str(tmp_path / "missing.npz"), "--out", str(out), "--quiet"]) == 1
    assert sorted(p.name for p in out.iterdir()) == ["results.md"]
