"""The priors and evaluate stages' run() on a tiny hand-built dataset directory."""

import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from deepword.priors import load_priors
from deepword.word_format import SUBSETS, open_dataset, write_records
from stages.evaluate.stage import run as run_evaluate
from stages.priors.stage import run as run_priors
from tests.deepword.tiny_word import build
from tests.stage_inputs import stage_inputs

PRIORS_CFG = {"mode": "prior", "components": [1, 3], "n_init": 1, "reg_covar": 1e-4, "max_fit_samples": 2000,
              "plot_bins": 30}
EVAL_CFG = {"min_box_px": 4, "match_iou": 0.5, "methods": ["logic", "logic_plus", "prior"],
            "box_sources": ["gt", "detected"], "fit_images": 60, "gallery_images": 2,
            "baseline_grids": OmegaConf.load(Path(__file__).parents[3] / "conf/eval/default.yaml").baseline_grids}


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    base = tmp_path_factory.mktemp("chain")
    data = build(base / "data", n_train=40, n_test=16)
    priors_dir = base / "priors"
    priors_dir.mkdir()
    pm = run_priors(OmegaConf.create({"priors": PRIORS_CFG, "seed": 0}), {"data": data}, priors_dir)
    return base, data, priors_dir, pm


def test_priors_stage_outputs(chain):
    _, _, priors_dir, metrics = chain
    assert 1 <= metrics["priors.wheel_vehicle.components"] <= 3
    assert 1 <= metrics["priors.wheel_wheel.components"] <= 3
    assert all(np.isfinite(v) for v in metrics.values())
    assert (priors_dir / "artifacts" / "priors.png").stat().st_size > 1000
    p = load_priors(priors_dir)
    v = p.wheel_vehicle(np.exp(np.linspace(-2, 3, 100)))
    assert v.min() >= 0 and v.max() <= 1 and v.max() > 0.9


def test_priors_stage_posterior_mode(chain, tmp_path):
    _, data, _, _ = chain
    cfg = OmegaConf.create({"priors": dict(PRIORS_CFG, mode="posterior"), "seed": 0})
    run_priors(cfg, {"data": data}, tmp_path)
    p = load_priors(tmp_path)
    assert p.wheel_wheel.mode == "posterior"
    v = p.wheel_wheel(np.exp(np.linspace(-2, 3, 100)))
    assert v.min() >= 0 and v.max() <= 1


def test_evaluate_stage_report_metrics_and_gallery(chain, tmp_path):
    _, data, priors_dir, _ = chain
    cfg = OmegaConf.create({"eval": EVAL_CFG, "seed": 0})
    metrics = run_evaluate(cfg, stage_inputs("evaluate", {"data": data, "priors": priors_dir}), tmp_path)
    for method in ("logic", "logic_plus", "prior"):
        for subset in SUBSETS:
            for m in ("wheel_acc", "pair_precision", "pair_recall", "pair_f1", "couple_f1", "image_acc"):
                assert 0 <= metrics[f"eval.gt.{method}.{subset}.{m}"] <= 100
    assert not any(k.startswith("eval.detected") for k in metrics)  # no detector input
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["results"]["gt"]["logic_plus"]["hard"]["wheel_acc"] == metrics["eval.gt.logic_plus.hard.wheel_acc"]
    md = (tmp_path / "report.md").read_text()
    assert "| logic_plus |" in md and "*92.91*" in md and "detected" in md  # skipped source noted
    assert (tmp_path / "artifacts" / "report.md").is_file()
    assert set(json.loads((tmp_path / "baselines.json").read_text())) == {"logic", "logic_plus", "prior"}
    gallery = sorted((tmp_path / "artifacts" / "gallery").glob("*.png"))
    assert 0 < len(gallery) <= 2
    assert metrics["eval.gt.logic_plus.mixed.wheel_acc"] > 90


def test_evaluate_stage_detected_boxes(chain, tmp_path):
    _, data, priors_dir, _ = chain
    ds = open_dataset(data)
    test = ds.subset("test")
    detector = tmp_path / "detector"
    detector.mkdir()
    # "detections": the ground-truth boxes shifted by one pixel, real-looking scores; one image missing
    shifted = []
    for r in test[1:]:
        b = r.boxes.copy()
        b[:, :4] += 1.0
        b[:, :4] = np.minimum(b[:, :4], [r.width, r.height, r.width, r.height])
        b[:, 4] = 0.9
        shifted.append(type(r)(**{**r.__dict__, "boxes": b, "relations": [], "wheel_pairs": []}))
    write_records(stage_inputs("evaluate", {"detector": detector}).output("detector", "predictions", split="test"),
                  shifted)
    out = tmp_path / "eval"
    out.mkdir()
    cfg = OmegaConf.create({"eval": dict(EVAL_CFG, methods=["logic"], gallery_images=0), "seed": 0})
    metrics = run_evaluate(cfg, stage_inputs("evaluate", {"data": data, "priors": priors_dir, "detector": detector}), out)
    gt, det = metrics["eval.gt.logic.easy.wheel_acc"], metrics["eval.detected.logic.easy.wheel_acc"]
    assert det <= gt and det > 50  # nearly the same boxes, but the missing image's wheels are all missed
    # the ceiling of these boxes: the truth's relations on them misses only the missing image's pairs
    ceiling = {s: metrics[f"eval.detected.relation_oracle.{s}.pair_f1"] for s in ("easy", "hard")}
    assert all(metrics[f"eval.detected.logic.{s}.pair_f1"] <= ceiling[s] for s in ceiling)
    assert min(ceiling.values()) < 100  # the subset of the missing image
    assert metrics["eval.detected.relation_oracle.hard.pair_precision"] == 100.0
    assert "gt.relation_oracle" not in " ".join(metrics)  # on ground-truth boxes it would be the truth itself
    report = (out / "report.md").read_text()
    assert "| relation_oracle |" in report and "is not a method" in report


def test_unknown_method_is_an_error(chain, tmp_path):
    _, data, priors_dir, _ = chain
    cfg = OmegaConf.create({"eval": dict(EVAL_CFG, methods=["oracle"]), "seed": 0})
    with pytest.raises(ValueError, match="unknown method 'oracle'"):
        run_evaluate(cfg, stage_inputs("evaluate", {"data": data, "priors": priors_dir}), tmp_path)


def test_evaluate_stage_scores_the_held_out_domain_beside_the_in_domain_rows(chain, tmp_path, monkeypatch):
    """The same dataset as `data` and as `shift_data`: every eval.shift row equals its in-domain row, and the
    held-out rows use the baselines fitted for the in-domain ones (each fitted once)."""
    import stages.evaluate.methods as methods

    _, data, priors_dir, _ = chain
    fits = []
    for name in ("logic", "logic_plus", "prior"):
        fit = methods.METHODS[name]
        monkeypatch.setitem(methods.METHODS, name, lambda ctx, fit=fit, name=name: fits.append(name) or fit(ctx))
    cfg = OmegaConf.create({"eval": dict(EVAL_CFG, box_sources=["gt"], gallery_images=0), "seed": 0})
    metrics = run_evaluate(cfg, stage_inputs("evaluate", {"data": data, "priors": priors_dir, "shift_data": data}), tmp_path)
    assert sorted(fits) == ["logic", "logic_plus", "prior"]
    in_domain = {k: v for k, v in metrics.items() if k.startswith("eval.gt.")}
    shifted = {k.replace("eval.shift.", "eval.", 1): v for k, v in metrics.items() if k.startswith("eval.shift.")}
    assert in_domain and shifted == in_domain
    assert "Held-out domain" in (tmp_path / "shift" / "report.md").read_text()
    assert (tmp_path / "artifacts" / "shift_report.md").is_file()
