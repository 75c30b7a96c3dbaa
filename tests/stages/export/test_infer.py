"""``deepword infer``: generated images and a dataset through the exported models, baselines with the
pipeline's fitted thresholds, no torch on the path, clear errors, and the MLflow run resolution."""

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from omegaconf import OmegaConf

from deepword.word_format import read_records
from stages.cli import main as deepword
from stages.inference.infer import main as infer

REPO = Path(__file__).parents[3]


def test_infer_on_generated_images_writes_predictions_and_overlays(exported, generated_images, tmp_path):
    out = tmp_path / "out"
    assert infer([*map(str, generated_images), "--out", str(out), "--export", str(exported[0])]) == 0
    preds = read_records(out / "labels.jsonl", root=generated_images[0].parent, check_images=True, allow_empty=True)
    assert [p.image for p in preds] == [p.name for p in generated_images]
    for pred, path in zip(preds, generated_images, strict=True):
        overlay = cv2.imread(str(out / "overlays" / f"{path.stem}.png"))
        assert overlay is not None and overlay.shape == cv2.imread(str(path)).shape
        assert (pred.width, pred.height) == (320, 240)
        ids = set(pred.box_ids.tolist())
        assert all(v in ids and w in ids for v, w, _ in pred.relations)


def test_infer_on_a_dataset_matches_the_evaluate_rows(upstream, exported, evaluated, tmp_path):
    for method in ("deepword", "logic", "prior", "deepword_then_logic"):
        out = tmp_path / method
        argv = ["--dataset", str(upstream["data"]), "--out", str(out), "--method", method, "--overlays", "2",
                "--export", str(exported[0]), "--evaluate", str(evaluated)]
        assert infer(argv) == 0
        got = {r.image: r for r in read_records(out / "labels.jsonl", root=upstream["data"])}
        want = read_records(evaluated / "predictions" / f"gt_{method}.jsonl", root=upstream["data"])
        assert want and all(got[w.image].relations == w.relations for w in want)
        assert all(got[w.image].wheel_pairs == w.wheel_pairs for w in want)
        overlays = sorted((out / "overlays").iterdir())
        assert len(overlays) == 2
        rec = next(iter(got.values()))
        original = cv2.imread(str(upstream["data"] / rec.image))
        drawn = cv2.imread(str(out / "overlays" / (Path(rec.image).with_suffix("").as_posix().replace("/", "__") + ".png")))
        assert drawn.shape == original.shape and np.abs(drawn.astype(int) - original).sum() > 0  # boxes drawn


def test_infer_with_detected_boxes_on_a_dataset(upstream, exported, tmp_path, capsys):
    argv = ["infer", "--dataset", str(upstream["data"]), "--detect", "--out", str(tmp_path), "--export", str(exported[0])]
    assert deepword(argv) == 0
    preds = read_records(tmp_path / "labels.jsonl", root=upstream["data"], allow_empty=True)
    gts = read_records(upstream["data"] / "labels.jsonl")
    assert len(preds) == len(gts)
    assert all(len(p.boxes) == 0 or (p.scores < 1).all() for p in preds)  # detector scores, not the annotation's
    # every detection beside them, for AP: the relations' boxes are those at the operating point among them
    every = {d.image: d for d in read_records(tmp_path / "detections.jsonl", root=upstream["data"], allow_empty=True)}
    assert set(every) == {p.image for p in preds}
    assert all(d.relations == [] for d in every.values())
    assert sum(len(d.boxes) for d in every.values()) >= sum(len(p.boxes) for p in preds)
    for p in preds:
        kept = {tuple(np.round(b[:5], 2)) for b in every[p.image].boxes}
        assert all(tuple(np.round(b[:5], 2)) in kept for b in p.boxes)
    assert deepword(["score", "--gt", str(upstream["data"]), "--pred", str(tmp_path / "labels.jsonl"),
                     "--detections", str(tmp_path / "detections.jsonl")]) == 0
    assert "## Where AP@0.5 goes (whole dataset)" in capsys.readouterr().out


def test_infer_runs_the_bundles_end_to_end_method_on_detected_boxes_and_deepword_on_given_ones(
        upstream, exported, evaluated, tmp_path, capsys):
    """Without --method: the bundle's end-to-end method (with its own fitted rule, no --evaluate) on detections,
    exactly the evaluate stage's row; DeepWORD on a dataset's own boxes."""
    for detect, method in ((True, "deepword_then_logic"), (False, "deepword")):
        out = tmp_path / method
        argv = ["--dataset", str(upstream["data"]), "--out", str(out), "--export", str(exported[0])]
        assert infer(argv + (["--detect"] if detect else [])) == 0
        assert f"method: {method}" in capsys.readouterr().err
        got = {r.image: r for r in read_records(out / "labels.jsonl", root=upstream["data"], allow_empty=True)}
        boxes = "detected" if detect else "gt"
        want = read_records(evaluated / "predictions" / f"{boxes}_{method}.jsonl", root=upstream["data"],
                            allow_empty=True)
        assert want and all(got[w.image].relations == w.relations for w in want)


def test_a_bundle_without_its_rule_falls_back_on_the_evaluate_stages_fit(upstream, exported, evaluated, tmp_path,
                                                                         capsys):
    import shutil

    bundle_dir = tmp_path / "old_bundle"
    shutil.copytree(exported[0], bundle_dir)
    bundle = json.loads((bundle_dir / "export.json").read_text())
    del bundle["end_to_end"]   # exported before bundles held their end-to-end method
    (bundle_dir / "export.json").write_text(json.dumps(bundle))
    base = ["--dataset", str(upstream["data"]), "--export", str(bundle_dir), "--method", "deepword_then_logic"]
    assert infer([*base, "--out", str(tmp_path / "no_rule")]) == 2
    assert "no fitted 'logic' rule" in capsys.readouterr().err
    out = tmp_path / "with_baselines"
    assert infer([*base, "--out", str(out), "--evaluate", str(evaluated)]) == 0
    got = {r.image: r for r in read_records(out / "labels.jsonl", root=upstream["data"])}
    want = read_records(evaluated / "predictions" / "gt_deepword_then_logic.jsonl", root=upstream["data"])
    assert all(got[w.image].relations == w.relations for w in want)
    # and such a bundle's end-to-end method is DeepWORD, the method its operating point was chosen by
    assert infer(["--dataset", str(upstream["data"]), "--detect", "--export", str(bundle_dir), "--out",
                  str(tmp_path / "old_default")]) == 0
    assert "method: deepword (the bundle's end-to-end method)" in capsys.readouterr().err


def test_infer_path_never_imports_torch(exported, generated_images, tmp_path):
    code = ("import sys; from stages.cli import main; "
            f"rc = main(['infer', {str(generated_images[0])!r}, '--out', {str(tmp_path)!r}, '--export', {str(exported[0])!r}]); "
            "assert rc == 0, rc; loaded = [m for m in ('torch', 'lightning') if m in sys.modules]; "
            "assert not loaded, loaded")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "labels.jsonl").is_file()


def test_unreadable_image_is_a_clear_error(exported, tmp_path, capsys):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    assert infer([str(bad), "--out", str(tmp_path / "o"), "--export", str(exported[0])]) == 2
    err = capsys.readouterr().err
    assert "broken.png" in err and "cannot read" in err and "Traceback" not in err


def test_dataset_that_fails_validation_is_a_clear_error(exported, upstream, tmp_path, capsys):
    root = tmp_path / "bad"
    root.mkdir()
    lines = (upstream["data"] / "labels.jsonl").read_text().splitlines()
    record = json.loads(lines[1])
    record["boxes"][0][5] = 7  # no such class
    (root / "labels.jsonl").write_text("\n".join([lines[0], json.dumps(record)]) + "\n")
    assert infer(["--dataset", str(root), "--out", str(tmp_path / "o"), "--export", str(exported[0])]) == 2
    err = capsys.readouterr().err
    assert "labels.jsonl:2" in err and "Traceback" not in err


def test_baseline_without_fitted_thresholds_is_a_clear_error(exported, upstream, tmp_path, capsys):
    argv = ["--dataset", str(upstream["data"]), "--out", str(tmp_path), "--method", "logic", "--export", str(exported[0])]
    assert infer(argv) == 2
    assert "baselines.json" in capsys.readouterr().err


@pytest.mark.slow  # MLflow creates a sqlite store (~20 s on 2 busy cores)
def test_run_id_resolves_to_the_runs_cache_entries(upstream, exported, evaluated, tmp_path, monkeypatch, capsys):
    """A pipeline-like MLflow record (parent run, stage child runs tagged with cache keys) and a cache
    directory laid out as the engine's: --run finds the export and evaluate entries; the newest run is
    the default."""
    import shutil

    from mlflow.tracking import MlflowClient

    from stages.inference.resolve import ResolveError, stage_dirs

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    exp = client.create_experiment("deepword")
    cache = tmp_path / "cache"
    parent = client.create_run(exp, tags={"profile": "smoke"}).info.run_id
    client.log_param(parent, "pipeline.cache_dir", str(cache))
    for stage, src in (("export", exported[0]), ("evaluate", evaluated)):
        shutil.copytree(src, cache / stage / f"key{stage}" / "out")
        child = client.create_run(exp, tags={"mlflow.parentRunId": parent, "stage": stage, "cache_key": f"key{stage}"})
        client.set_terminated(child.info.run_id)
    client.set_terminated(parent)
    monkeypatch.delenv("DEEPWORD_CACHE", raising=False)
    run_id, dirs = stage_dirs(None, uri)
    assert run_id == parent and dirs["export"] == cache / "export" / "keyexport" / "out"
    out = tmp_path / "o"
    argv = ["--dataset", str(upstream["data"]), "--out", str(out), "--method", "logic", "--tracking-uri", uri]
    assert infer([*argv, "--run", parent]) == 0
    want = read_records(evaluated / "predictions" / "gt_logic.jsonl", root=upstream["data"])
    got = {r.image: r for r in read_records(out / "labels.jsonl", root=upstream["data"])}
    assert all(got[w.image].relations == w.relations for w in want)
    assert infer([*argv, "--run", "0123456789abcdef"]) == 2
    assert "0123456789abcdef" in capsys.readouterr().err
    # this run has no detector stage (pipeline.skip=[detector]): detection needs another run, said clearly
    with pytest.raises(ResolveError, match=r"no finished pipeline run with the stages \['detector', 'export'\]"):
        stage_dirs(None, uri, need_detector=True)
    assert infer([*argv, "--run", parent, "--detect"]) == 2
    assert f"run {parent} has no detector" in capsys.readouterr().err


def test_deepword_command_dispatches_and_rejects_unknown_commands(capsys):
    assert deepword(["frobnicate"]) == 2
    assert "unknown command" in capsys.readouterr().err
    with pytest.raises(SystemExit) as done:
        deepword(["score", "--help"])
    assert done.value.code == 0 and "--pred" in capsys.readouterr().out


def test_infer_with_a_calibration_file_writes_footprints_and_a_top_view(exported, generated_images, tmp_path, capsys):
    from deepword.footprint import FootprintPrior
    from deepword.inference.footprints import PRIOR_FILE

    bev = tmp_path / "bev"
    bev.mkdir()
    prior = FootprintPrior(width=1.8, length=4.5, wheelbase=2.7, length_slope=1.0, length_offset=1.8,
                           track_inset=0.1, contact_shift=0.3, box_shift=2.5, height=1.5)
    (bev / PRIOR_FILE).write_text(json.dumps(prior.to_json()))
    image = generated_images[1]
    out = tmp_path / "out"
    args = [str(image), "--out", str(out), "--export", str(exported[0]), "--bev", str(bev)]
    assert infer([*args, "--calibration", str(image.with_suffix(".json"))]) == 0
    pred = read_records(out / "labels.jsonl", root=image.parent)[0]
    vehicles = {int(b) for b, c in zip(pred.box_ids, pred.class_ids, strict=True) if c == 0}
    assert {int(k) for k, v in pred.extra["objects_3d"].items() if "center" in v} == vehicles
    overlay = cv2.imread(str(out / "overlays" / f"{image.stem}.png"))
    # the top view beside the 320 x 240 overlay, its legend whole below the map: 24 px title + 320 px map + 56 px
    # legend tall, the overlay padded with white below
    assert overlay.shape == (400, 320 + 320, 3)
    assert (overlay[240:, :320] == 255).all() and (overlay[-56:, 320:] < 128).any()

    bad = json.loads(image.with_suffix(".json").read_text())
    bad["intrinsic"]["width"] = 640
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    assert infer([*args, "--calibration", str(tmp_path / "bad.json")]) == 2
    err = capsys.readouterr().err
    assert "bad.json: field 'intrinsic.width'" in err and "Traceback" not in err


def test_flip_averaged_relation_scores_do_not_depend_on_which_way_the_image_faces(exported, upstream, tmp_path):
    """``relation.decode.flip_average``: the scores are the mean over the graph and its mirror image, so an
    image and its mirror image get the same scores; without it they differ."""
    import shutil

    from deepword.inference.runtime import BUNDLE_FILE, OnnxRelation
    from deepword.relation_graph import mirrored
    from deepword.word_format import load_image, open_dataset

    out, _ = exported
    bundle = tmp_path / "bundle"
    shutil.copytree(out, bundle)
    meta = json.loads((bundle / BUNDLE_FILE).read_text())
    meta["relation"]["decode"]["flip_average"] = True
    (bundle / BUNDLE_FILE).write_text(json.dumps(meta))
    ds = open_dataset(upstream["data"])
    plain, averaged = OnnxRelation(out), OnnxRelation(bundle)
    assert averaged.flip_average and not plain.flip_average
    recs = ds.subset("test")[:4]
    graphs = [plain.graph(r, load_image(ds.root, r)) for r in recs]
    flipped = [mirrored(g) for g in graphs]
    a, b = averaged.scores(graphs), averaged.scores(flipped)
    p, q = plain.scores(graphs), plain.scores(flipped)
    for k in range(3):  # owner, couple, front
        assert np.allclose(a[k], b[k], atol=1e-6)
        assert np.allclose(a[k], (p[k] + q[k]) / 2, atol=1e-6)
    assert not np.allclose(p[0], q[0], atol=1e-4)


def _calibrated_frame(tmp_path):
    """A rendered frame's four images as a dataset whose records carry their calibration, and a bev stage output
    with a footprint prior: (dataset root, bev dir)."""
    from deepword.footprint import FootprintPrior
    from deepword.inference.footprints import PRIOR_FILE
    from deepword.word_format import write_dataset_index, write_records
    from stages.data.synword import FrameGenerator

    cfg = OmegaConf.to_container(OmegaConf.load(REPO / "conf/data/synword.yaml"), resolve=True)
    cfg["image_size"] = [320, 240]
    data = tmp_path / "data"
    records = []
    for camera, rgb, rec in FrameGenerator(cfg, seed=0).render_frame(0):
        (data / "images").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(data / "images" / f"{camera}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        records.append(replace(rec, image=f"images/{camera}.png"))
    write_records(data / "labels.jsonl", records)
    write_dataset_index(data, data, {"test": [r.image for r in records]})
    bev = tmp_path / "bev"
    bev.mkdir()
    prior = FootprintPrior(width=1.8, length=4.5, wheelbase=2.7, length_slope=1.0, length_offset=1.8,
                           track_inset=0.1, contact_shift=0.3, box_shift=2.5, height=1.5)
    (bev / PRIOR_FILE).write_text(json.dumps(prior.to_json()))
    return data, bev


def test_infer_with_detected_boxes_on_a_calibrated_dataset_writes_footprints(exported, tmp_path, capsys):
    """A dataset whose records carry their calibration gives footprints on detected boxes too: the detections keep
    their image's camera."""
    data, bev = _calibrated_frame(tmp_path)
    out = tmp_path / "out"
    assert infer(["--dataset", str(data), "--detect", "--out", str(out), "--export", str(exported[0]),
                  "--bev", str(bev)]) == 0
    preds = read_records(out / "labels.jsonl", root=data, allow_empty=True)
    assert all("calibration" in p.extra and "objects_3d" in p.extra for p in preds)
    assert (out / "footprints.jsonl").is_file()
    # on the dataset's own boxes DeepWORD claims wheels: their roles are read from the footprints, and infer says so
    capsys.readouterr()
    assert infer(["--dataset", str(data), "--out", str(tmp_path / "own"), "--export", str(exported[0]),
                  "--bev", str(bev)]) == 0
    own = read_records(tmp_path / "own" / "labels.jsonl", root=data)
    assert any(p.relations for p in own) and all("roles_from" in p.extra for p in own if p.relations)
    assert "wheel roles read from: footprint " in capsys.readouterr().out


def test_infer_places_the_footprint_points_vehicles_and_writes_the_operating_points_relations(exported, tmp_path,
                                                                                             monkeypatch):
    """With a footprint point below the operating point, infer runs the relations once more on the weaker vehicles'
    detections for the footprints; labels.jsonl holds the operating point's boxes and relations as without it, each
    naming only its own boxes, and the footprints place the weaker vehicles too."""
    import shutil

    import numpy as np

    from deepword.inference.runtime import BUNDLE_FILE
    from stages.inference import infer as infer_module

    data, bev = _calibrated_frame(tmp_path)

    class TruthAsDetections(infer_module.OnnxDetector):
        """Each image's true boxes as detections: its first vehicle scored 0.2, every other box 0.9."""

        def detect_every(self, rgb, source):
            boxes = source.boxes.copy()
            boxes[:, 4] = 0.9
            vehicles = np.flatnonzero(boxes[:, 5] == 0)
            boxes[vehicles[:1], 4] = 0.2
            return replace(source, boxes=boxes, relations=[], wheel_pairs=[])

    monkeypatch.setattr(infer_module, "OnnxDetector", TruthAsDetections)
    outs = {}
    for name, point in (("with", {"vehicle": 0.1}), ("without", {})):
        bundle_dir = tmp_path / f"bundle_{name}"
        shutil.copytree(exported[0], bundle_dir)
        bundle = json.loads((bundle_dir / BUNDLE_FILE).read_text())
        bundle["detector"].update(operating_point={"vehicle": 0.5, "wheel": 0.5}, min_side={}, footprint_point=point)
        (bundle_dir / BUNDLE_FILE).write_text(json.dumps(bundle))
        outs[name] = tmp_path / f"out_{name}"
        assert infer(["--dataset", str(data), "--detect", "--out", str(outs[name]), "--export", str(bundle_dir),
                      "--bev", str(bev)]) == 0
    preds = {n: read_records(outs[n] / "labels.jsonl", root=data, allow_empty=True) for n in outs}
    for a, b in zip(preds["with"], preds["without"], strict=True):
        assert np.array_equal(a.boxes, b.boxes) and [r[:2] for r in a.relations] == [r[:2] for r in b.relations]
        assert {int(k) for k in a.extra["objects_3d"]} <= set(a.box_ids.tolist())
        assert (a.scores[a.class_ids == 0] == 0.9).all()

    def footprints(out) -> int:
        return sum(len(json.loads(line)["footprints"]) for line in (out / "footprints.jsonl").read_text().splitlines())

    assert footprints(outs["with"]) > footprints(outs["without"])
