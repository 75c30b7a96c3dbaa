"""The export stage on a tiny dataset with randomly initialised networks: files, checker, parity, metrics."""

import json

import numpy as np
import onnx
import pytest

from deepword.inference.runtime import BUNDLE_FILE, DETECTOR_FILE, RELATION_FILES


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
    assert bundle["detector"]["footprint_point"] == {"vehicle": 0.1}   # a null class keeps the operating point's
    assert metrics["export.detector.operating_point_evaluations"] == 9 * 2
    assert 0 < metrics["export.detector.operating_point_relation_runs"] <= 18 * 6   # each distinct subset once
    assert metrics["export.detector.val_pair_f1"] >= metrics["export.detector.val_pair_f1_at_score_threshold"]
    assert (out / "artifacts" / "latency.md").read_text().count("|") > 20
    # what the search saw: the chosen point and its val pair_f1 in the table, and the two cuts as a figure
    table = (out / "artifacts" / "operating_point.md").read_text()
    chosen = f"| **chosen** | {op['vehicle']:.2f} | {op['wheel']:.2f} |"
    assert chosen in table and f"**{metrics['export.detector.val_pair_f1']:.2f}**" in table
    assert (out / "artifacts" / "operating_point.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_bundle_detector_keeps_what_its_operating_point_keeps(exported, tmp_path):
    """Inference applies the bundle's thresholds and minimum sides, and a bundle without minimum sides (exported
    before they existed) keeps every size."""
    import shutil

    from deepword.inference.runtime import OnnxDetector
    from deepword.word_format import Record

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


def test_the_footprints_take_the_operating_points_boxes_under_their_ids_and_weaker_vehicles_after_them(exported,
                                                                                                     tmp_path):
    """The footprint point keeps every box the operating point keeps, with the ids keep_operating_point gives them,
    and the vehicles between the two thresholds numbered after them; a footprint threshold above the operating
    point's does not raise it, and a bundle without one (or from before it existed) keeps the operating point's."""
    import shutil

    from deepword.inference.runtime import OnnxDetector
    from deepword.word_format import Record

    out, _ = exported
    bundle_dir = tmp_path / "bundle"
    shutil.copytree(out, bundle_dir)
    bundle = json.loads((bundle_dir / BUNDLE_FILE).read_text())
    bundle["detector"].update(operating_point={"vehicle": 0.3, "wheel": 0.2}, min_side={"wheel": 8.0})
    # by falling score: a vehicle, a 20 px wheel, a 5 px wheel, a weak vehicle, a weaker one, a weak 20 px wheel
    every = Record(image="images/front/000001.png", frame_id=1, camera="front", width=200, height=100,
                   boxes=np.array([[10, 10, 110, 70, 0.9, 0, 0], [15, 50, 35, 70, 0.8, 1, 1],
                                   [60, 62, 65, 67, 0.6, 1, 2], [120, 10, 190, 60, 0.25, 0, 3],
                                   [130, 20, 180, 50, 0.12, 0, 4], [85, 50, 105, 70, 0.15, 1, 5]]),
                   relations=[], wheel_pairs=[], extra={"facing": {"0": [1.0, 0.0], "3": [0.0, 1.0]}})
    for point, scores, ids in (({"vehicle": 0.2}, [0.9, 0.8, 0.25], [0, 1, 2]),
                               ({"vehicle": 0.1, "wheel": 0.5}, [0.9, 0.8, 0.25, 0.12], [0, 1, 2, 3]),
                               ({"vehicle": 0.6}, [0.9, 0.8], [0, 1]),
                               (None, [0.9, 0.8], [0, 1])):
        bundle["detector"].pop("footprint_point", None)
        if point is not None:
            bundle["detector"]["footprint_point"] = point
        (bundle_dir / BUNDLE_FILE).write_text(json.dumps(bundle))
        detector = OnnxDetector(bundle_dir)
        relations = detector.keep_operating_point(every)
        footprints = detector.keep_footprint_point(every)
        assert relations.scores.tolist() == [0.9, 0.8] and relations.box_ids.tolist() == [0, 1]
        assert footprints.scores.tolist() == scores and footprints.box_ids.tolist() == ids
    # the detector's facing vectors follow their boxes' new ids
    bundle["detector"]["footprint_point"] = {"vehicle": 0.2}
    (bundle_dir / BUNDLE_FILE).write_text(json.dumps(bundle))
    assert OnnxDetector(bundle_dir).keep_footprint_point(every).extra["facing"] == {"0": [1.0, 0.0], "2": [0.0, 1.0]}


@pytest.mark.parametrize("point, message", [
    ({"car": 0.2}, "export.footprint_point: unknown class 'car'; known: vehicle, wheel"),
    ({"vehicle": 1.5}, "export.footprint_point.vehicle: 1.5 is not a score in [0, 1]"),
])
def test_a_bad_footprint_point_is_refused_naming_the_key(point, message):
    from omegaconf import OmegaConf

    from stages.export.stage import footprint_thresholds

    with pytest.raises(ValueError) as err:
        footprint_thresholds(OmegaConf.create({"footprint_point": point}))
    assert str(err.value) == message
    assert footprint_thresholds(OmegaConf.create({"footprint_point": {"vehicle": 0.2, "wheel": None}})) == \
        {"vehicle": 0.2}


def test_the_bundle_ships_its_end_to_end_method_and_the_rule_it_falls_back_on(upstream, exported, evaluated):
    """The IoU rule in the bundle is the evaluate stage's fit of its own `logic` row, and the operating point's val
    pair_f1 is the end-to-end method's: the bundle's detector at its operating point, then the bundle's method."""
    from deepword.inference.runtime import OnnxDetector, bundle_method, end_to_end_method
    from deepword.metrics import score_records
    from deepword.word_format import load_image, open_dataset

    out, metrics = exported
    bundle = json.loads((out / BUNDLE_FILE).read_text())
    assert end_to_end_method(out) == bundle["end_to_end"]["method"] == "deepword_then_logic"
    fitted = json.loads((evaluated / "baselines.json").read_text())
    assert bundle["end_to_end"]["rules"] == {"logic": fitted["logic"]}
    ds = open_dataset(upstream["data"])
    val, detector = ds.subset("val"), OnnxDetector(out)
    detected = [detector.detect(load_image(ds.root, r), r) for r in val]
    for name, key in (("deepword_then_logic", "val_pair_f1"), ("deepword", "val_pair_f1_deepword")):
        method = bundle_method(name, out, ds.root)
        preds = {d.image: method.predict(d) for d in detected}
        f1 = score_records(val, preds, 4.0, 0.5).percentages()["pair_f1"]
        assert f1 == pytest.approx(metrics[f"export.detector.{key}"], abs=1e-9), name


def test_an_unknown_end_to_end_method_fails_before_anything_is_exported(upstream):
    from omegaconf import OmegaConf

    from deepword.word_format import open_dataset
    from stages.export.stage import end_to_end_entry

    cfg = OmegaConf.create({"method": "deepword_then_iou", "fit": {"images": 5, "couple_tolerance": [0.5],
                                                                   "logic_iou": [0.1]}})
    with pytest.raises(ValueError, match=r"export\.end_to_end\.method: 'deepword_then_iou'"):
        end_to_end_entry(open_dataset(upstream["data"]), cfg, 4.0, 0)
    entry, fallback = end_to_end_entry(open_dataset(upstream["data"]), OmegaConf.merge(cfg, {"method": "deepword"}),
                                       4.0, 0)
    assert entry["method"] == "deepword" and fallback is None and set(entry["rules"]) == {"logic"}


def test_a_val_prior_split_joins_the_search_weighed_and_the_val_figures_stay_the_val_splits(upstream, exported,
                                                                                          tmp_path):
    """A composed dataset's val_prior split (the generator's val beside a new camera's few val images) adds its counts,
    weighed as ``prior_images`` val images; the metrics named val_* stay the val split's own. Weighed as nothing it
    changes nothing; weighed as a million images it chooses what ``deepword tune`` chooses on those images alone."""
    import shutil

    from omegaconf import OmegaConf

    from deepword.inference.runtime import bundle_rule, end_to_end_method
    from deepword.rules.fallback import FALLBACKS
    from deepword.word_format import PRIOR_SPLIT, open_dataset
    from stages.export.stage import choose_operating_point
    from stages.inference.tune import main as tune
    from tests.stages.export.tiny_models import EXPORT_CFG

    out, shipped = exported
    bundle = json.loads((out / BUNDLE_FILE).read_text())
    ds = open_dataset(upstream["data"])
    ds.splits[PRIOR_SPLIT] = list(ds.splits["test"])
    fallback = bundle_rule(out, FALLBACKS[end_to_end_method(out)][1])

    def choose(weight):
        work = tmp_path / f"w{weight}"
        shutil.copytree(out, work)
        op = OmegaConf.create({**EXPORT_CFG["operating_point"], "prior_images": weight})
        return choose_operating_point(ds, work, bundle["detector"], op, float(EXPORT_CFG["min_box_px"]), None, 1e-4,
                                      fallback, "deepword_then_logic"), work

    (thresholds, sides, metrics), _ = choose(0)
    assert metrics["export.detector.val_pair_f1"] == pytest.approx(shipped["export.detector.val_pair_f1"])
    assert "export.detector.prior_images" not in metrics and thresholds == bundle["detector"]["operating_point"]
    (thresholds, sides, metrics), work = choose(1e6)
    assert metrics["export.detector.prior_images"] == 1e6
    assert metrics["export.detector.prior_split_images"] == len(ds.splits["test"])
    assert "with the val_prior split" in (work / "artifacts" / "operating_point.md").read_text()
    assert tune(["--dataset", str(upstream["data"]), "--split", "test", "--export", str(out),
                 "--out", str(tmp_path / "on_test")]) == 0
    alone = json.loads((tmp_path / "on_test" / BUNDLE_FILE).read_text())["tuned"]
    assert metrics["export.detector.val_pair_f1_with_prior"] == pytest.approx(alone["pair_f1"], abs=1e-3)
