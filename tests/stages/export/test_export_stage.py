"""The export stage on a tiny dataset with randomly initialised networks: files, checker, parity, metrics."""

import json

import onnx
import pytest

from stages.inference.runtime import BUNDLE_FILE, DETECTOR_FILE, RELATION_FILES


def test_stage_writes_checked_models_and_metrics(exported):
    out, metrics = exported
    for name in (*RELATION_FILES.values(), DETECTOR_FILE):
        onnx.checker.check_model(onnx.load(str(out / name)), full_check=True)
    assert metrics["export.relation.parity_max_abs_diff"] <= 1e-4
    assert metrics["export.relation.parity_decision_agreement"] >= 99.9
    assert metrics["export.detector.parity_max_abs_diff"] <= 1e-4
    assert metrics["export.relation.parity_pairs"] > 0
    for key in ("ms_per_img_b1", "ms_per_10img_b10", "params", "size_mb"):
        for model in ("relation", "detector"):
            assert metrics[f"export.{model}.{key}"] > 0
    for b in ("ms_per_img_b1", "ms_per_10img_b10"):  # real object counts; static padded; the references
        for prefix in ("", "cpu_", "static_", "static_cpu_", "torch_"):
            assert metrics[f"export.relation.{prefix}{b}"] > 0
    assert metrics["export.relation.speedup_vs_torch"] == pytest.approx(
        metrics["export.relation.torch_ms_per_img_b1"] / metrics["export.relation.ms_per_img_b1"])
    bundle = json.loads((out / BUNDLE_FILE).read_text())
    assert bundle["metrics"] == pytest.approx(metrics)
    # the operating point chosen on val ships with the detector, and is the best of the pairs it tried
    op = bundle["detector"]["operating_point"]
    assert set(op) == {"vehicle", "wheel"} and all(t in (0.1, 0.3, 0.5) for t in op.values())
    assert metrics["export.detector.threshold.vehicle"] == op["vehicle"]
    assert metrics["export.detector.operating_point_evaluations"] == 9
    assert metrics["export.detector.val_pair_f1"] >= metrics["export.detector.val_pair_f1_at_score_threshold"]
    assert (out / "artifacts" / "latency.md").read_text().count("|") > 20
