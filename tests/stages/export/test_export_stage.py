"""The export stage on a tiny dataset with randomly initialised networks: files, checker, parity, metrics."""

import json

import numpy as np
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
    assert bundle["detector"]["min_side"] == {"vehicle": 0.0, "wheel": metrics["export.detector.min_side.wheel"]}
    assert bundle["detector"]["min_side"]["wheel"] in (0.0, 4.0)
    assert metrics["export.detector.operating_point_evaluations"] == 9 * 2
    assert 0 < metrics["export.detector.operating_point_relation_runs"] <= 18 * 6   # each distinct subset once
    assert metrics["export.detector.val_pair_f1"] >= metrics["export.detector.val_pair_f1_at_score_threshold"]
    assert (out / "artifacts" / "latency.md").read_text().count("|") > 20


def test_a_bundle_detector_keeps_what_its_operating_point_keeps(exported, tmp_path):
    """Inference applies the bundle's thresholds and minimum sides, and a bundle without minimum sides (exported
    before they existed) keeps every size."""
    import shutil

    from stages.inference.runtime import OnnxDetector
    from stages.word_format import Record

    out, _ = exported
    bundle_dir = tmp_path / "bundle"
    shutil.copytree(out, bundle_dir)
    bundle = json.loads((bundle_dir / BUNDLE_FILE).read_text())
    bundle["detector"]["operating_point"] = {"vehicle": 0.3, "wheel": 0.2}
    # a vehicle, a weak vehicle, a 20 px wheel, a 5 px wheel, a weak 20 px wheel
    every = Record(image="images/front/000001.png", frame_id=1, camera="front", width=200, height=100,
                   boxes=np.array([[10, 10, 110, 70, 0.9, 0, 0], [120, 10, 190, 60, 0.25, 0, 1],
                                   [15, 50, 35, 70, 0.8, 1, 2], [60, 62, 65, 67, 0.6, 1, 3],
                                   [85, 50, 105, 70, 0.15, 1, 4]]), relations=[], wheel_pairs=[])
    for min_side, scores in (({"wheel": 8.0}, [0.9, 0.8]), (None, [0.9, 0.8, 0.6])):
        bundle["detector"].pop("min_side", None)
        if min_side is not None:
            bundle["detector"]["min_side"] = min_side
        (bundle_dir / BUNDLE_FILE).write_text(json.dumps(bundle))
        kept = OnnxDetector(bundle_dir).keep_operating_point(every)
        assert kept.scores.tolist() == scores and kept.box_ids.tolist() == list(range(len(scores)))
