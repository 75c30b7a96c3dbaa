"""The evaluate stage with the export stage as input: DeepWORD rows and detected boxes come from ONNX."""

import json

from omegaconf import OmegaConf

from stages.evaluate.stage import run as run_evaluate

EVAL_CFG = {"min_box_px": 4, "match_iou": 0.5, "methods": ["logic", "deepword", "deepword_int8"],
            "box_sources": ["gt", "detected"], "fit_images": 20, "gallery_images": 0}


def test_evaluate_runs_the_onnx_rows_on_both_box_sources(upstream, exported, tmp_path):
    export_dir, metrics = exported
    inputs = {"data": upstream["data"], "priors": upstream["priors"], "export": export_dir}
    out = run_evaluate(OmegaConf.create({"eval": EVAL_CFG, "seed": 0}), inputs, tmp_path)
    report = json.loads((tmp_path / "report.json").read_text())
    assert set(report["results"]) == {"gt", "detected"}
    for boxes in ("gt", "detected"):
        assert set(report["results"][boxes]) == {"logic", "deepword", "deepword_int8"}
    # the export stage's own FP32/INT8 accuracies (same ONNX models, same test split) match the report
    for subset in ("easy", "hard", "mixed"):
        assert out[f"eval.gt.deepword.{subset}.wheel_acc"] == metrics[f"export.relation.fp32.{subset}.wheel_acc"]
        assert out[f"eval.gt.deepword_int8.{subset}.wheel_acc"] == metrics[f"export.relation.int8.{subset}.wheel_acc"]
