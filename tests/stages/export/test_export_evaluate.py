"""The evaluate stage with the export stage as input: DeepWORD rows and detected boxes come from ONNX."""

import json


def test_evaluate_runs_the_onnx_rows_on_both_box_sources(exported, evaluated):
    _, metrics = exported
    report = json.loads((evaluated / "report.json").read_text())
    assert set(report["results"]) == {"gt", "detected"}
    for boxes in ("gt", "detected"):
        assert set(report["results"][boxes]) == {"logic", "prior", "deepword", "deepword_int8"}
    # the export stage's own FP32/INT8 accuracies (same ONNX models, same test split) match the report
    for subset in ("easy", "hard", "mixed"):
        gt = report["results"]["gt"]
        assert gt["deepword"][subset]["wheel_acc"] == metrics[f"export.relation.fp32.{subset}.wheel_acc"]
        assert gt["deepword_int8"][subset]["wheel_acc"] == metrics[f"export.relation.int8.{subset}.wheel_acc"]
