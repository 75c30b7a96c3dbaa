"""The data stage end to end: synword (determinism, parallel == serial, outputs, metrics) and data=word."""

import json

import cv2
import numpy as np
import pytest
from omegaconf import OmegaConf

from deepword.word_format import DatasetError, open_dataset
from stages.data.stage import run
from stages.data.synword import FrameGenerator, generate
from tests.stages.data.data_helpers import synword_cfg

METRICS = [f"data.{s}.{m}" for s in ("train", "val", "test")
           for m in ("images", "vehicles_per_image", "wheels_per_image", "multi_box_wheel_share")]


def test_same_seed_same_frame_different_seed_differs():
    cfg = synword_cfg(size=(160, 120))
    a, b, c = FrameGenerator(cfg, 5), FrameGenerator(cfg, 5), FrameGenerator(cfg, 6)
    fa, fb, fc = a.render_frame(2), b.render_frame(2), c.render_frame(2)
    for (_, img_a, rec_a), (_, img_b, rec_b) in zip(fa, fb, strict=True):
        assert rec_a.to_json() == rec_b.to_json()
        assert img_a.tobytes() == img_b.tobytes()
    assert any(ra.to_json() != rc.to_json() or not np.array_equal(ia, ic)
               for (_, ia, ra), (_, ic, rc) in zip(fa, fc, strict=True))


@pytest.mark.slow
def test_parallel_generation_matches_serial(tmp_path):
    cfg = synword_cfg(frames=3, size=(160, 120))
    serial = generate(cfg, 11, tmp_path / "s", workers=1, progress=False)
    parallel = generate(cfg, 11, tmp_path / "p", workers=2, progress=False)
    assert [r.to_json() for r in serial] == [r.to_json() for r in parallel]
    for r in serial:
        assert (tmp_path / "s" / r.image).read_bytes() == (tmp_path / "p" / r.image).read_bytes()


def test_a_renderer_process_holds_opencv_and_openblas_to_one_thread(tmp_path):
    """Two renderer processes on two cores: each one thread, else OpenBLAS's own threads oversubscribe the cores
    (docs/results.md, "Where the time goes")."""
    from threadpoolctl import threadpool_info

    from stages.data import synword

    cv2_threads = cv2.getNumThreads()
    synword._init_worker(synword_cfg(frames=1, size=(160, 120)), 11, str(tmp_path))   # as the pool starts a process
    try:
        assert cv2.getNumThreads() == 1
        blas = [pool for pool in threadpool_info() if pool["user_api"] == "blas"]
        assert blas and all(pool["num_threads"] == 1 for pool in blas)
    finally:
        synword._WORKER.pop("blas").restore_original_limits()
        synword._WORKER.clear()
        cv2.setNumThreads(cv2_threads)


def test_run_synword_smoke(tmp_path):
    cfg = OmegaConf.create({"data": synword_cfg(frames=5, size=(160, 120)), "seed": 3})
    metrics = run(cfg, {}, tmp_path)
    for key in METRICS + ["data.test.easy_images", "data.test.hard_images"]:
        assert key in metrics and np.isfinite(metrics[key])
    ds = open_dataset(tmp_path)
    assert ds.root == tmp_path.resolve()
    assert json.loads((tmp_path / "dataset.json").read_text())["root"] == "."  # relative: the dir moves
    assert sum(metrics[f"data.{s}.images"] for s in ("train", "val", "test")) == len(ds.records)
    assert set(ds.splits) >= {"train", "val", "test", "easy", "hard", "mixed"}
    assert cv2.imread(str(tmp_path / "artifacts" / "contact_sheet.png")) is not None


def _write_word(root, lines):
    (root / "images" / "front").mkdir(parents=True)
    for f in range(3):
        cv2.imwrite(str(root / "images" / "front" / f"{f}.png"), np.zeros((60, 80, 3), np.uint8))
    (root / "labels.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")


def _rec(f, boxes, relations):
    return {"image": f"images/front/{f}.png", "frame_id": f, "camera": "front", "width": 80, "height": 60,
            "boxes": boxes, "relations": relations}


def test_run_word_validates_and_points_at_the_external_root(tmp_path):
    root = tmp_path / "mydata"
    v, w = [5, 5, 60, 50, 1.0, 0, 1], [10, 35, 20, 50, 1.0, 1, 2]
    _write_word(root, [_rec(0, [v, w], [[1, 2, "rear"]]), _rec(1, [v], []), _rec(2, [v, w], [[1, 2]])])
    out = tmp_path / "out"
    out.mkdir()
    cfg = OmegaConf.create({"data": {"name": "word", "root": str(root), "watch": [],
                                     "split": {"train": 0.4, "val": 0.3, "test": 0.3}, "max_easy_vehicles": 3},
                            "seed": 0})
    metrics = run(cfg, {}, out)
    assert json.loads((out / "dataset.json").read_text())["root"] == str(root.resolve())
    assert not (out / "images").exists() and not (out / "labels.jsonl").exists()  # nothing copied
    ds = open_dataset(out)
    assert len(ds.records) == 3 and metrics["data.test.images"] + metrics["data.train.images"] \
        + metrics["data.val.images"] == 3


def test_run_word_names_file_line_and_field_of_a_broken_record(tmp_path):
    root = tmp_path / "broken"
    v = [5, 5, 60, 50, 1.0, 0, 1]
    _write_word(root, [_rec(0, [v], []), _rec(1, [v, [30, 10, 20, 40, 1.0, 1, 2]], [])])
    cfg = OmegaConf.create({"data": {"name": "word", "root": str(root), "watch": [],
                                     "split": {"train": 0.4, "val": 0.3, "test": 0.3}, "max_easy_vehicles": 3},
                            "seed": 0})
    with pytest.raises(DatasetError) as err:
        run(cfg, {}, tmp_path / "out")
    assert err.value.line == 2 and err.value.field == "boxes[1]"
    assert "labels.jsonl:2" in str(err.value) and "x1 < x2" in str(err.value)


def test_run_word_missing_image(tmp_path):
    root = tmp_path / "missing"
    _write_word(root, [_rec(7, [[5, 5, 60, 50, 1.0, 0, 1]], [])])
    cfg = OmegaConf.create({"data": {"name": "word", "root": str(root), "watch": [],
                                     "split": {"train": 0.4, "val": 0.3, "test": 0.3}, "max_easy_vehicles": 3},
                            "seed": 0})
    with pytest.raises(DatasetError, match=r"labels.jsonl:1: field 'image'"):
        run(cfg, {}, tmp_path / "out")
