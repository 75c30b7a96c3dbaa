"""Upstream stage outputs for the export tests, built in seconds: a drawn WORD dataset (rows of side-view
cars, nearer ones lower and larger), priors fitted by the priors stage, a small randomly initialised
relation network and a small randomly initialised CenterNet, saved exactly as their stages save them."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from deepword.word_format import Record, difficulty_subsets, write_dataset_index, write_records
from tests.car_rows import CarRows
from tests.stages.export.tiny_models import DETECTOR, EXPORT_CFG, MAX_OBJECTS, PRIORS_CFG, RELATION_MODEL

W, H = 160, 120
SCENES = CarRows(W, H, car=(80, 34), nearness=(0.5, 1.0), bottom=(50, 60))


def draw(rec: Record, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((H, W, 3), 150, dtype=np.uint8)
    for b in sorted((b for b in rec.boxes if b[5] == 0), key=lambda b: b[3]):
        colour = tuple(int(c) for c in rng.integers(60, 255, 3))
        cv2.rectangle(img, (int(b[0]), int(b[1])), (int(b[2]), int(b[3])), colour, -1)
    for w in rec.boxes[rec.boxes[:, 5] == 1]:
        centre = (int((w[0] + w[2]) / 2), int((w[1] + w[3]) / 2))
        cv2.circle(img, centre, max(int((w[2] - w[0]) / 2), 1), (20, 20, 20), -1)
    return img


def build_dataset(root: Path, n: int = 14, seed: int = 0) -> Path:
    """A data-stage-like directory: labels.jsonl, PNGs, dataset.json, splits.json (test has easy and hard)."""
    rng = np.random.default_rng(seed)
    records = []
    for i in range(n):
        boxes, relations, pairs = SCENES.car_row(rng, int(rng.integers(1, 6)))
        rec = Record(image=f"images/left/{i:05d}.png", frame_id=i, camera="left", width=W, height=H, boxes=boxes,
                     relations=relations, wheel_pairs=pairs, scene="parking")
        (root / rec.image).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / rec.image), cv2.cvtColor(draw(rec, seed + i), cv2.COLOR_RGB2BGR))
        records.append(rec)
    write_records(root / "labels.jsonl", records)
    images = [r.image for r in records]
    n_test = n // 2
    splits = {"train": images[: n - n_test - 1], "val": images[n - n_test - 1: n - n_test], "test": images[n - n_test:]}
    splits.update(difficulty_subsets(records[n - n_test:], seed))
    write_dataset_index(root, root, splits)
    return root


def save_relation(out: Path, seed: int = 0) -> Path:
    from deepword.relation_graph import InputConfig
    from stages.relation.model import ModelConfig, RelationNet

    torch.manual_seed(seed)
    out.mkdir(parents=True, exist_ok=True)
    net = RelationNet(ModelConfig(**RELATION_MODEL)).eval()
    torch.save(net.state_dict(), out / "relation.pt")
    inputs = InputConfig(input_size=RELATION_MODEL["backbone"]["input_size"], max_objects=MAX_OBJECTS)
    (out / "relation.json").write_text(json.dumps({
        "model": RELATION_MODEL, "inputs": asdict(inputs), "decode": {"threshold": 0.5, "one_owner": True},
        "has_roles": True, "seed": seed, "metrics": {"relation.val.wheel_acc": 50.0}}))
    return out


def save_detector_dir(out: Path, seed: int = 0) -> Path:
    from stages.detector.model import build_centernet, model_config, save_detector

    torch.manual_seed(seed)
    out.mkdir(parents=True, exist_ok=True)
    config = model_config(DETECTOR)
    save_detector(out, build_centernet(config).eval(), config)
    return out


@pytest.fixture(scope="session")
def upstream(tmp_path_factory) -> dict[str, Path]:
    """{stage name: output directory} of data, priors, relation and detector."""
    from stages.priors.stage import run as run_priors

    base = tmp_path_factory.mktemp("upstream")
    data = build_dataset(base / "data")
    priors = base / "priors"
    priors.mkdir()
    run_priors(OmegaConf.create({"priors": PRIORS_CFG, "seed": 0}), {"data": data}, priors)
    return {"data": data, "priors": priors, "relation": save_relation(base / "relation"),
            "detector": save_detector_dir(base / "detector")}


@pytest.fixture(scope="session")
def exported(upstream, tmp_path_factory) -> tuple[Path, dict[str, float]]:
    """The export stage run once on ``upstream``: (its output directory, its metrics)."""
    from stages.export.stage import run

    out = tmp_path_factory.mktemp("export")
    torch.set_num_threads(1)
    metrics = run(OmegaConf.create({"export": EXPORT_CFG, "seed": 0}), upstream, out)
    return out, metrics


@pytest.fixture(scope="session")
def evaluated(upstream, exported, tmp_path_factory) -> Path:
    """The evaluate stage run once with the export stage as input (its fitted baselines and predictions)."""
    from stages.evaluate.stage import run

    out = tmp_path_factory.mktemp("evaluate")
    cfg = {"min_box_px": 4, "match_iou": 0.5, "methods": ["logic", "prior", "deepword", "deepword_int8",
                                                     "deepword_then_logic"],
           "box_sources": ["gt", "detected"], "fit_images": 20, "gallery_images": 2,
           "baseline_grids": OmegaConf.load(Path(__file__).parents[3] / "conf/eval/default.yaml").baseline_grids}
    run(OmegaConf.create({"eval": cfg, "seed": 0}), {**upstream, "export": exported[0]}, out)
    return out


@pytest.fixture(scope="session")
def generated_images(tmp_path_factory) -> list[Path]:
    """The four camera images of one frame of the project's own synthetic generator (320x240)."""
    from stages.data.synword import FrameGenerator

    cfg = OmegaConf.to_container(OmegaConf.load(Path(__file__).parents[3] / "conf/data/synword.yaml"), resolve=True)
    cfg["image_size"] = [320, 240]
    cfg["lens"]["randomise"] = False  # the nominal rig: every image 320x240
    out = tmp_path_factory.mktemp("frame")
    paths = []
    for camera, rgb, rec in FrameGenerator(cfg, seed=0).render_frame(0):
        paths.append(out / f"{camera}.png")
        cv2.imwrite(str(paths[-1]), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        # each camera's calibration as a WoodScape-style JSON file beside its image
        (out / f"{camera}.json").write_text(json.dumps({**rec.extra["calibration"], "name": camera}))
    return paths
