"""aefabmap_eval: the four methods on a tiny synthetic sequence, --model, --train-on-test, recordings and
every bad input (ERROR: ..., exit 1)."""

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pytest

from aefabmap_ros.cli import synth
from aefabmap_ros.cli.evaluate import main
from aefabmap_ros.evaluation.metrics import evaluate_scores
from aefabmap_ros.verification.geometric import VerificationConfig

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


RecordedClosure = tuple[int, int, float] | tuple[int, int, float, int]  # query, place, probability[, inliers]


def write_recording(path: Path, posteriors: list[tuple[int, list[int], list[float]]],
                    closures: Mapping[str, Sequence[RecordedClosure]]) -> None:
    """A recording with ``/place_posteriors`` and one LoopClosure topic per key of ``closures``."""
    from aefabmap_ros.io import bags

    types = bags.get_typestore().types
    start = 1_700_000_000_000_000_000
    period = 100_000_000
    with bags.BagWriter(path) as writer:
        writer.add_topic("/place_posteriors", "aefabmap_msgs/msg/PlacePosterior")
        for topic in closures:
            writer.add_topic(topic, "aefabmap_msgs/msg/LoopClosure")
        for query, places, probabilities in posteriors:
            message = types["aefabmap_msgs/msg/PlacePosterior"](
                header=bags.make_header(start + query * period), query_id=query, assigned_place_id=query,
                current_place_id=query,
                is_new_place=True, loop_closure_candidate=False, new_place_probability=1.0 - sum(probabilities),
                place_ids=np.array(places, dtype=np.int64),
                place_stamps=[bags.make_time(start + p * period) for p in places],
                probabilities=np.array(probabilities, dtype=np.float64),
                log_likelihoods=np.zeros(len(places), dtype=np.float64),
            )
            writer.write("/place_posteriors", start + query * period, message)
        for topic, entries in closures.items():
            for query, place, probability, *inliers in entries:
                message = types["aefabmap_msgs/msg/LoopClosure"](
                    header=bags.make_header(start + query * period), query_id=query, query_place_id=place,
                    matched_place_id=place, matched_stamp=bags.make_time(start + place * period),
                    probability=probability, log_likelihood=0.0, inliers=inliers[0] if inliers else -1,
                    **bags.no_pose_fields(),
                )
                writer.write(topic, start + query * period, message)


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
    np.savez(tmp_path / "gt.npz", gt=gt)
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
    assert results["place_posteriors"] == frames and results["event_gap_frames"] == 3
    raw, verified = results["closures"]
    # Candidates: 12 -> 0 and 16 -> 4 true, 18 -> 2 false; the one event (12..19) closed; frames 12, 16 of 8.
    assert raw == {"role": "FAB-MAP candidates", "topic": "loop_closure_candidates", "closures": 3, "verified": 0,
                   "false_closures": 1, "precision": pytest.approx(2 / 3), "revisit_events": 1, "events_closed": 1,
                   "fraction_of_events_closed": 1.0, "revisiting_frames": 8, "revisiting_frames_closed": 2,
                   "recall_revisiting_frames": 0.25, "missed_revisiting_frames_with_a_true_place_ranked": 6}
    assert verified == {"role": "published", "topic": "loop_closures", "closures": 1, "verified": 1,
                        "false_closures": 0, "precision": 1.0, "revisit_events": 1, "events_closed": 1,
                        "fraction_of_events_closed": 1.0, "revisiting_frames": 8, "revisiting_frames_closed": 1,
                        "recall_revisiting_frames": 0.125, "missed_revisiting_frames_with_a_true_place_ranked": 7}
    # Every revisiting frame had its true place among its recorded top places: each miss is the decision's.
    assert "| published | `loop_closures` | 1 | 1 | 0 | 1.000 | 1 | 1 | 1.000 | 0.125 (1/8) | 7 / 7 |" in printed
    row = "| FAB-MAP candidates | `loop_closure_candidates` | 3 | 0 | 1 | 0.667 | 1 | 1 | 1.000 | 0.250 (2/8) | 6 / 6 |"
    assert row in (tmp_path / "out" / "results.md").read_text()
    assert (tmp_path / "out" / "scores_recording.png").is_file()


def _three_event_gt() -> np.ndarray:
    """40 frames, min gap 10. Event A: 12, 13, 14, 15, 17 (one frame missing: bridged); event B: 25..28
    (each revisits two frames 19-20 back); event C: 35 (revisits 20). 10 revisiting frames."""
    gt = np.zeros((40, 40), np.uint8)
    for query, place in ((12, 0), (13, 1), (14, 2), (15, 3), (17, 5), (35, 20)):
        gt[query, place] = 1
    for query in range(25, 29):
        gt[query, [query - 20, query - 19]] = 1
    return gt


def test_recording_events_and_an_older_recording(tmp_path, capsys):
    """An older recording (verified_loop_closures): its loop_closures are the candidates, its
    verified_loop_closures the published closures; both scored per revisit event, by hand."""
    np.savez(tmp_path / "gt.npz", gt=_three_event_gt())
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


def test_recording_of_two_layouts_at_once_is_refused(tmp_path, capsys):
    np.savez(tmp_path / "gt.npz", gt=_three_event_gt())
    write_recording(tmp_path / "mixed", [(13, [], [])], {"/loop_closure_candidates": [(13, 1, 0.999)],
                                                         "/verified_loop_closures": [(13, 1, 0.999, 40)]})
    err = run_error(["--recording", str(tmp_path / "mixed"), "--gt", str(tmp_path / "gt.npz"),
                     "--out", str(tmp_path / "out")], capsys)
    assert "has both verified_loop_closures" in err and "loop_closure_candidates" in err


def test_recording_without_the_topics(tmp_path, capsys):
    from aefabmap_ros.io import bags

    bags.write_image_bag(tmp_path / "images", "/image", [(1, np.zeros((4, 4), np.uint8))])
    np.savez(tmp_path / "gt.npz", gt=np.zeros((3, 3), np.uint8))
    err = run_error(["--recording", str(tmp_path / "images"), "--gt", str(tmp_path / "gt.npz"),
                     "--out", str(tmp_path / "out")], capsys)
    assert "has none of place_posteriors, loop_closures, loop_closure_candidates" in err


def test_recording_with_query_beyond_the_ground_truth(tmp_path, capsys):
    write_recording(tmp_path / "run", [(0, [], []), (5, [0], [0.5])], {})
    np.savez(tmp_path / "gt.npz", gt=np.zeros((3, 3), np.uint8))
    err = run_error(["--recording", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.npz"),
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
