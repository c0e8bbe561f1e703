"""The evaluation's markdown and JSON reports."""

from aefabmap_ros.evaluation.protocol import EvaluationConfig, MethodResult, evaluate_model
from aefabmap_ros.evaluation.reports import result_to_dict, results_markdown, unique_slugs
from test.evaluation.test_protocol import openfabmap, small_model_and_features


def test_reports():
    model, features, gt = small_model_and_features()
    results = evaluate_model(model, features, gt, ("FABMAP2", "BoW"), EvaluationConfig(min_gap=3), openfabmap())
    results[1].label = "office/v2"
    table = results_markdown(results).splitlines()
    assert len(table) == 4 and table[2].startswith("| FABMAP2 | kmeans 30 | 1.000 |")
    assert table[3].startswith("| BoW (office/v2) | kmeans 30 |")
    entry = result_to_dict(results[0])
    assert entry["recall_at_100_precision"] == 1.0 and entry["method"] == "FABMAP2"
    assert len(entry["pr_curve"]["precision"]) == len(entry["pr_curve"]["recall"]) >= 1
    assert unique_slugs(results) == ["fabmap2", "bow_office_v2"]
    twin = MethodResult(**{**results[0].__dict__})
    assert unique_slugs([results[0], twin]) == ["fabmap2", "fabmap2_2"]
