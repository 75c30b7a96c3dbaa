"""``deepword infer`` in bounded memory: decoded images kept within a budget (``DecodedImages``), the same predictions
whatever the budget, and progress lines over a dataset."""

import numpy as np
import pytest

from stages.inference import infer as infer_module
from stages.inference.image_cache import DecodedImages
from stages.inference.infer import main as infer


def _image(value: int, nbytes: int = 100) -> np.ndarray:
    return np.full(nbytes, value, np.uint8)


def test_the_least_recently_used_images_go_once_the_budget_is_spent():
    cache = DecodedImages(budget_bytes=250)
    loads = []

    def load(key):
        loads.append(key)
        return _image(key)

    for key in (1, 2):
        cache.get(key, lambda k=key: load(k))
    assert cache.get(1, lambda: load(1))[0] == 1 and loads == [1, 2]   # held: not decoded again
    cache.get(3, lambda: load(3))                                       # 300 bytes > 250: 2, the least recent, goes
    assert 2 not in cache and 1 in cache and 3 in cache and cache.bytes == 200
    cache.get(2, lambda: load(2))
    assert loads == [1, 2, 3, 2] and cache.decodes == 4


def test_an_image_larger_than_the_budget_is_still_handed_over():
    cache = DecodedImages(budget_bytes=0)
    assert cache.get("a", lambda: _image(7))[0] == 7
    cache.put("b", _image(8))
    assert len(cache) == 1 and "b" in cache and cache.bytes == 100
    with pytest.raises(ValueError, match="budget"):
        DecodedImages(budget_bytes=-1)


def test_predictions_do_not_depend_on_the_image_memory_and_a_dataset_shows_progress(upstream, exported, tmp_path,
                                                                                    capsys, monkeypatch):
    monkeypatch.setattr(infer_module, "PROGRESS_MIN_IMAGES", 1)   # the smoke dataset is smaller than a real one
    outs = {}
    for budget in ("2048", "0"):   # all images kept / each pass decodes every image again
        out = tmp_path / budget
        assert infer(["--dataset", str(upstream["data"]), "--detect", "--out", str(out), "--export", str(exported[0]),
                      "--image-memory-mb", budget]) == 0
        outs[budget] = (out / "labels.jsonl").read_bytes(), (out / "detections.jsonl").read_bytes()
        err = capsys.readouterr().err
        assert "detector: " in err and "relations (deepword_then_logic): " in err
    assert outs["2048"] == outs["0"]
    assert infer(["--dataset", str(upstream["data"]), "--out", str(tmp_path / "x"), "--export", str(exported[0]),
                  "--image-memory-mb", "-1"]) == 2
    assert "--image-memory-mb -1: expected 0 or more" in capsys.readouterr().err


def test_loose_images_are_read_once_up_front_and_an_image_given_twice_is_an_error(exported, generated_images,
                                                                                  tmp_path, capsys):
    first = str(generated_images[0])
    assert infer([first, first, "--out", str(tmp_path / "out"), "--export", str(exported[0])]) == 2
    assert f"{first}: the same image is given twice" in capsys.readouterr().err
    # a budget smaller than one image: every pass decodes the loose images again, with the same predictions
    outs = []
    for budget in ("2048", "0"):
        out = tmp_path / budget
        assert infer([*map(str, generated_images), "--out", str(out), "--export", str(exported[0]),
                      "--image-memory-mb", budget]) == 0
        outs.append((out / "labels.jsonl").read_bytes())
    assert outs[0] == outs[1]
