"""The evaluate stage with the export stage as input: DeepWORD rows and detected boxes come from ONNX."""

import json
from pathlib import Path

import numpy as np


def test_evaluate_runs_the_onnx_rows_on_both_box_sources(exported, evaluated):
    _, metrics = exported
    report = json.loads((evaluated / "report.json").read_text())
    assert set(report["results"]) == {"gt", "detected"}
    assert report["end_to_end"] == "deepword_then_logic"   # the bundle's, for the bev stage's top views
    methods = {"logic", "prior", "deepword", "deepword_int8", "deepword_then_logic"}
    assert set(report["results"]["gt"]) == methods
    assert set(report["results"]["detected"]) == methods | {"relation_oracle"}  # the ceiling of the detections
    ceiling = report["results"]["detected"]["relation_oracle"]
    for subset in ("easy", "hard", "mixed"):
        assert ceiling[subset]["pair_precision"] == 100.0
        assert all(report["results"]["detected"][m][subset]["pair_f1"] <= ceiling[subset]["pair_f1"] for m in methods)
    # the export stage's own FP32/INT8 accuracies (same ONNX models, same test split) match the report
    for subset in ("easy", "hard", "mixed"):
        gt = report["results"]["gt"]
        assert gt["deepword"][subset]["wheel_acc"] == metrics[f"export.relation.fp32.{subset}.wheel_acc"]
        assert gt["deepword_int8"][subset]["wheel_acc"] == metrics[f"export.relation.int8.{subset}.wheel_acc"]
    # end to end first: the headline table (detected beside ground-truth boxes, the detector's operating
    # point), then the detected-box tables before the ground-truth-box ones
    md = (evaluated / "report.md").read_text()
    assert md.index("## End to end") < md.index("## detected boxes") < md.index("## ground-truth boxes")
    assert "Operating point" in md
    # the bundle's end-to-end method leads, DeepWORD alone beside it
    lead = md[md.index("## End to end"):md.index("## detected boxes")]
    assert lead.startswith("## End to end: `deepword_then_logic` on detected boxes")
    assert lead.index("| detected boxes (end-to-end) | deepword_then_logic |") < \
        lead.index("| detected boxes (end-to-end) | deepword |") < lead.index("| ground-truth boxes | deepword |")
    assert "pair_f1 of `deepword_then_logic`" in lead
    # each box source's tables end with the pair errors by cause, which add up to the pairs the scores count
    assert md.index("## detected boxes") < md.index("## Where the pair errors are: detected boxes") < \
        md.index("## ground-truth boxes")
    for boxes in ("gt", "detected"):
        for subset in ("easy", "hard", "mixed"):
            e = report["pair_errors"][boxes]["deepword"][subset]
            missed = e["wheel_missed"] + e["vehicle_missed"] + e["not_paired"]
            false = e["false_wheel"] + e["false_vehicle"] + e["wrong_pair"]
            scores = report["results"][boxes]["deepword"][subset]
            recall = 100.0 * e["found"] / (e["found"] + missed) if e["found"] + missed else 100.0
            precision = 100.0 * e["found"] / (e["found"] + false) if e["found"] + false else 100.0
            assert recall == scores["pair_recall"] and precision == scores["pair_precision"]
    assert all(report["pair_errors"]["gt"]["deepword"][s]["wheel_missed"] == 0 for s in ("easy", "hard", "mixed"))
    # DeepWORD, then the IoU rule: every DeepWORD claim kept, so it finds every pair DeepWORD finds
    for boxes in ("gt", "detected"):
        for subset in ("easy", "hard", "mixed"):
            errors = report["pair_errors"][boxes]
            assert errors["deepword_then_logic"][subset]["found"] >= errors["deepword"][subset]["found"]
    from deepword.word_format import read_records

    by_method = {m: {r.image: r for r in read_records(evaluated / "predictions" / f"detected_{m}.jsonl",
                                                      allow_empty=True)}
                 for m in ("deepword", "deepword_then_logic")}
    for image, rec in by_method["deepword"].items():
        combined = by_method["deepword_then_logic"][image].relations
        assert combined[:len(rec.relations)] == rec.relations
        wheels = [w for _, w, _ in combined]
        assert len(wheels) == len(set(wheels))

    # disagreements drawn on both box sources, at most eval.gallery_images each (the toy detector's methods may agree)
    assert 0 < len(list((evaluated / "artifacts" / "gallery").glob("*.png"))) <= 2
    assert len(list((evaluated / "artifacts" / "gallery_detected").glob("*.png"))) <= 2


def test_evaluate_writes_each_rows_predictions_on_the_footprint_points_detections(evaluated):
    """For the bev stage: every row on the detections of the bundle's footprint point (vehicles down to 0.1 here),
    written beside the scored predictions; their boxes are the scored ones under the same ids, and weaker vehicles."""
    from deepword.word_format import read_records

    report = json.loads((evaluated / "report.json").read_text())
    for method in report["results"]["detected"]:
        if method == "relation_oracle":
            continue
        scored = {r.image: r for r in read_records(evaluated / "predictions" / f"detected_{method}.jsonl",
                                                   allow_empty=True)}
        placed = {r.image: r for r in read_records(evaluated / "predictions" / f"footprints_{method}.jsonl",
                                                   allow_empty=True)}
        assert placed.keys() == scored.keys()
        for image, rec in scored.items():
            more = placed[image]
            by_id = {int(b[6]): b for b in more.boxes}
            assert all(np.array_equal(by_id[int(b[6])], b) for b in rec.boxes)
            extra = [b for i, b in by_id.items() if i not in set(rec.box_ids.tolist())]
            assert all(b[5] == 0 and 0.1 <= b[4] for b in extra)
            assert sorted(by_id) == list(range(len(more.boxes)))


def test_without_a_detector_the_bundle_is_relation_only_and_evaluate_scores_ground_truth_boxes(upstream, tmp_path):
    """``pipeline.skip=[detector]`` (the paper tables' sweeps): export and evaluate run without it."""
    import pytest
    from omegaconf import OmegaConf

    from deepword.inference.runtime import BUNDLE_FILE, DETECTOR_FILE, NoDetectorError, OnnxDetector
    from stages.evaluate.stage import run as evaluate
    from stages.export.stage import run as export
    from tests.stages.export.tiny_models import EXPORT_CFG

    relation_only = {k: v for k, v in upstream.items() if k != "detector"}
    out = tmp_path / "export"
    out.mkdir()
    metrics = export(OmegaConf.create({"export": EXPORT_CFG, "seed": 0}), relation_only, out)
    assert not (out / DETECTOR_FILE).exists() and json.loads((out / BUNDLE_FILE).read_text())["detector"] is None
    assert metrics["export.relation.ms_per_img_b1"] > 0 and metrics["export.relation.parity_max_abs_diff"] <= 1e-4
    assert not [k for k in metrics if k.startswith("export.detector.")]
    assert "detector" not in (out / "artifacts" / "latency.md").read_text()
    with pytest.raises(NoDetectorError, match="pipeline.skip=\\[detector\\]"):
        OnnxDetector(out)

    ev = tmp_path / "evaluate"
    ev.mkdir()
    cfg = {"min_box_px": 4, "match_iou": 0.5, "methods": ["logic", "deepword"], "box_sources": ["gt", "detected"],
           "fit_images": 20, "gallery_images": 0,
           "baseline_grids": OmegaConf.load(Path(__file__).parents[3] / "conf/eval/default.yaml").baseline_grids}
    evaluate(OmegaConf.create({"eval": cfg, "seed": 0}), {**relation_only, "export": out}, ev)
    report = json.loads((ev / "report.json").read_text())
    assert set(report["results"]) == {"gt"} and set(report["results"]["gt"]) == {"logic", "deepword"}
    assert any("`detected` boxes skipped" in n for n in report["notes"])


def test_held_out_ap_sweeps_every_detection_while_relations_see_the_operating_point(upstream, monkeypatch):
    """Relations are scored on the detections at the operating point, the AP on every detection down to the
    detector's score_threshold: a precision-recall curve cut at the operating point would understate it."""
    from dataclasses import replace

    from deepword.word_format.dataset import open_dataset
    from stages.evaluate import methods

    class FakeDetector:
        """Each test image's true boxes as detections scored 0.2 and 0.6 in turn; 0.5 the operating point."""

        def __init__(self, bundle_dir, threads=1):
            sessions.append(threads)

        def detect_every(self, rgb, source):
            boxes = source.boxes.copy()
            boxes[:, 4] = [0.2 if k % 2 else 0.6 for k in range(len(boxes))]
            return replace(source, boxes=boxes, relations=[], wheel_pairs=[])

        def keep_operating_point(self, record):
            return replace(record, boxes=record.boxes[record.boxes[:, 4] >= 0.5])

    from omegaconf import OmegaConf

    sessions = []
    monkeypatch.setattr(methods, "OnnxDetector", FakeDetector)  # the name evaluate builds its detector with
    dataset = open_dataset(upstream["data"])
    ctx = methods.EvalContext(cfg=OmegaConf.create({"threads": 2}), seed=0,
                              inputs={**upstream, "export": upstream["data"]}, dataset=dataset, priors=None)
    every, at_point = methods.detections_for_ap(ctx), methods.detected_boxes(ctx)
    assert sessions == [2]  # one detector pass serves both, with eval.threads
    assert [r.image for r in every] == list(at_point) == [r.image for r in dataset.subset("test")]
    assert any((r.scores == 0.2).any() for r in every)
    assert all((r.scores == 0.6).all() for r in at_point.values())
    # without an export (a relation-only run) there is nothing to measure
    assert methods.detections_for_ap(methods.EvalContext(cfg=None, seed=0, inputs=upstream, dataset=dataset,
                                                         priors=None)) is None


def test_the_rows_share_each_image_and_deepwords_predictions(upstream, exported, tmp_path, monkeypatch):
    """Every row runs on one image before the next: ``deepword`` and ``deepword_int8`` decode it once between
    them, and ``deepword_then_logic`` adds to ``deepword``'s predictions instead of running the model again."""
    from omegaconf import OmegaConf

    import stages.evaluate.methods as methods
    from deepword.inference.runtime import OnnxRelation
    from deepword.word_format import open_dataset
    from stages.evaluate.stage import run

    decoded, relation_runs = [], []
    load = methods.load_image
    monkeypatch.setattr(methods, "load_image", lambda root, rec: decoded.append(rec.image) or load(root, rec))
    predict_many = OnnxRelation.predict_many

    def counted(self, records, load_rgb):
        relation_runs.append([r.image for r in records])
        return predict_many(self, records, load_rgb)

    monkeypatch.setattr(OnnxRelation, "predict_many", counted)
    cfg = {"min_box_px": 4, "match_iou": 0.5, "methods": ["deepword", "deepword_int8", "deepword_then_logic"],
           "box_sources": ["gt"], "fit_images": 20, "gallery_images": 0,
           "baseline_grids": OmegaConf.load(Path(__file__).parents[3] / "conf/eval/default.yaml").baseline_grids}
    run(OmegaConf.create({"eval": cfg, "seed": 0}), {**upstream, "export": exported[0]}, tmp_path)
    test_images = [r.image for r in open_dataset(upstream["data"]).subset("test")]
    assert sorted(decoded) == sorted(test_images)                     # once each, for both models
    assert sorted(relation_runs) == sorted([[i] for i in test_images] * 2)   # fp32 and int8, not fp32 twice
    # and the rows are what they were: deepword_then_logic starts with deepword's own claims
    from deepword.word_format import read_records

    rows = {m: {r.image: r for r in read_records(tmp_path / "predictions" / f"gt_{m}.jsonl", allow_empty=True)}
            for m in ("deepword", "deepword_then_logic")}
    for image, rec in rows["deepword"].items():
        assert rows["deepword_then_logic"][image].relations[:len(rec.relations)] == rec.relations
