import cv2
import numpy as np
import pytest
import torch

from deepword.word_format import Record
from stages.detector.dataset import CenterNetDataset, crop_boxes


def test_crop_boxes_shifts_clips_and_drops_mostly_hidden_boxes():
    xyxy = np.array([[10, 10, 30, 30],     # inside
                     [-10, 0, 10, 20],     # half outside on the left: kept at min_visible 0.5, clipped
                     [35, 0, 60, 10],      # 1/5 inside: dropped
                     [100, 100, 110, 110]  # outside
                     ], dtype=float) + [5, 5, 5, 5]
    kept, keep = crop_boxes(xyxy, 5, 5, 40, 30, min_visible=0.5)
    assert keep.tolist() == [True, True, False, False]
    assert np.allclose(kept, [[10, 10, 30, 30], [0, 0, 10, 20]])
    assert crop_boxes(xyxy, 5, 5, 40, 30, min_visible=0.1)[1].tolist() == [True, True, True, False]


def write_image(root, width=96, height=64) -> Record:
    """White squares on black: three 'vehicles' (class 0) and one 'wheel' (class 1)."""
    boxes = np.array([[4, 4, 20, 20, 1, 0, 0], [40, 10, 60, 30, 1, 0, 1], [70, 30, 90, 60, 1, 0, 2],
                      [44, 30, 50, 36, 1, 1, 3]], dtype=float)
    image = np.zeros((height, width, 3), dtype=np.uint8)
    for x1, y1, x2, y2 in boxes[:, :4].astype(int):
        image[y1:y2, x1:x2] = 255
    (root / "images").mkdir()
    cv2.imwrite(str(root / "images/a.png"), image)
    return Record(image="images/a.png", frame_id=0, camera="front", width=width, height=height, boxes=boxes,
                  relations=[], wheel_pairs=[])


@pytest.mark.parametrize("flip", [0.0, 1.0])
def test_random_crops_keep_image_and_boxes_consistent(tmp_path, flip):
    record = write_image(tmp_path)
    augment = {"flip": flip, "brightness": 0.0, "contrast": 0.0, "saturation": 0.0, "crop": [64, 32],
               "crop_min_visible": 0.5}
    dataset = CenterNetDataset(tmp_path, [record], 96, 64, max_objects=8, augment=augment)
    torch.manual_seed(0)
    seen = set()
    for _ in range(20):
        image, xyxy, classes, facings = dataset.augmented(*dataset.letterboxed(0))
        assert image.shape == (32, 64, 3) and len(xyxy) == len(classes) == len(facings)
        for x1, y1, x2, y2 in np.round(xyxy).astype(int):
            assert image[y1:y2, x1:x2].min() == 255              # every kept box lies on its white square
        seen.add(len(xyxy))
    assert len(seen) > 1  # the crops moved
    item = dataset[0]
    assert item["image"].shape == (32, 64, 3) and item["image"].dtype == torch.uint8 and item["hm"].shape == (2, 8, 16)
    assert int(item["mask"].sum()) == int((item["hm"] == 1).sum())  # one peak per kept object


@pytest.mark.parametrize("crop", [[64, 32], None])
def test_multi_scale_keeps_image_and_boxes_consistent(tmp_path, crop):
    record = write_image(tmp_path)
    augment = {"flip": 0.5, "brightness": 0.0, "contrast": 0.0, "saturation": 0.0, "scale": [0.6, 1.4],
               "crop": crop, "crop_min_visible": 0.5}
    dataset = CenterNetDataset(tmp_path, [record], 96, 64, max_objects=8, augment=augment)
    torch.manual_seed(1)
    sizes = set()
    for _ in range(20):
        image, xyxy, _, _ = dataset.augmented(*dataset.letterboxed(0))
        assert image.shape == ((32, 64, 3) if crop else (64, 96, 3))  # cropped or padded to the training size
        for x1, y1, x2, y2 in xyxy:
            # the inner part of every box lies on its white square (edges blur when resized)
            inner = image[int(np.ceil(y1)) + 1:int(y2) - 1, int(np.ceil(x1)) + 1:int(x2) - 1]
            assert inner.size == 0 or inner.min() >= 250
            sizes.add(round(float(x2 - x1), 1))
    assert len(sizes) > 4  # the scale changed


def test_mosaic_boxes_lie_on_their_objects_from_four_images(tmp_path):
    """Every box of a mosaic lies on its white square whichever of the four images it came from, and a mosaic
    holds more boxes than the one image has (the four images are drawn from the dataset: here one image, four
    times)."""
    record = write_image(tmp_path)
    augment = {"flip": 0.5, "brightness": 0.0, "contrast": 0.0, "saturation": 0.0, "scale": [0.8, 1.2],
               "crop": [64, 32], "crop_min_visible": 0.5, "mosaic": 1.0, "mosaic_scale": [0.5, 1.0]}
    dataset = CenterNetDataset(tmp_path, [record], 96, 64, max_objects=4, augment=augment)
    assert dataset.max_objects == 16  # room for four images' boxes
    torch.manual_seed(2)
    counts = []
    for _ in range(30):
        image, xyxy, labels = dataset.mosaic(*dataset.letterboxed(0), np.random.default_rng(len(counts)))
        assert image.shape == (32, 64, 3)  # the training window, cut from the mosaic
        classes = labels[:, 0]
        assert len(xyxy) == len(classes) and set(classes.tolist()) <= {0, 1}
        for x1, y1, x2, y2 in xyxy:
            inner = image[int(np.ceil(y1)) + 1:int(y2) - 1, int(np.ceil(x1)) + 1:int(x2) - 1]
            assert inner.size == 0 or inner.min() >= 250
        counts.append(len(xyxy))
    assert max(counts) > 4  # boxes of more than one image
    item = dataset[0]  # through the crop, jitter and targets
    assert item["image"].shape == (32, 64, 3) and item["mask"].shape == (16,)


def test_close_mosaic_trains_the_last_epochs_on_single_images(tmp_path, monkeypatch):
    """``CloseMosaic`` shuts the mosaic for the last epochs only, and a closed dataset draws no mosaic even at
    probability 1."""
    from types import SimpleNamespace

    from stages.detector.lightning import CloseMosaic

    record = write_image(tmp_path)
    augment = {"flip": 0.5, "brightness": 0.0, "contrast": 0.0, "saturation": 0.0, "crop": [64, 32],
               "crop_min_visible": 0.5, "mosaic": 1.0, "mosaic_scale": [0.5, 1.0]}
    dataset = CenterNetDataset(tmp_path, [record], 96, 64, max_objects=4, augment=augment)
    trainer = SimpleNamespace(max_epochs=10, current_epoch=0, datamodule=SimpleNamespace(train_set=dataset))
    opened = []
    for epoch in range(10):
        trainer.current_epoch = epoch
        CloseMosaic(3).on_train_epoch_start(trainer, None)
        opened.append(bool(dataset.mosaic_open))
    assert opened == [True] * 7 + [False] * 3
    monkeypatch.setattr(dataset, "mosaic", lambda *a: pytest.fail("a mosaic was drawn after closing"))
    torch.manual_seed(3)
    for _ in range(5):
        image, _, _, _ = dataset.augmented(*dataset.letterboxed(0))
        assert image.shape == (32, 64, 3)


def test_sensor_effects_keep_the_image_shape_and_type():
    from stages.detector.augment import sensor_effects

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)
    out = sensor_effects(image, rng, blur=1.0, noise=1.0, jpeg=1.0, grayscale=1.0)
    assert out.shape == image.shape and out.dtype == np.uint8 and not np.array_equal(out, image)
    assert np.array_equal(out[..., 0], out[..., 1]) and np.array_equal(out[..., 1], out[..., 2])
    assert sensor_effects(image, rng) is image  # every probability 0: untouched


def test_evaluation_items_are_the_whole_letterboxed_image(tmp_path):
    record = write_image(tmp_path)
    dataset = CenterNetDataset(tmp_path, [record], 96, 64, max_objects=8, augment=None)
    item = dataset[0]
    assert item["image"].shape == (64, 96, 3) and int(item["mask"].sum()) == 4
    assert dataset.letterboxed(0)[0] is dataset.letterboxed(0)[0]  # decoded once, then cached
    with pytest.raises(ValueError, match="larger than the input size"):
        CenterNetDataset(tmp_path, [record], 96, 64, 8, augment={"crop": [128, 32]})


def test_preloaded_images_are_the_lazily_loaded_ones_and_loader_processes_share_them(tmp_path, monkeypatch):
    """DetectorDataModule.setup decodes every image once, with threads, before loader processes are forked: the
    processes then read that cache and never decode an image themselves."""
    import stages.detector.dataset as dataset_module
    from stages.detector.lightning import DetectorDataModule

    record = write_image(tmp_path)
    records = [Record(image=record.image, frame_id=i, camera="front", width=record.width, height=record.height,
                      boxes=record.boxes, relations=[], wheel_pairs=[]) for i in range(6)]
    lazy = CenterNetDataset(tmp_path, records, 96, 64, max_objects=8)
    data = DetectorDataModule(tmp_path, records, records[:2], 96, 64, {"flip": 0.5, "brightness": 0.2, "contrast": 0.2,
                              "saturation": 0.2}, batch_size=2, num_workers=2, min_overlap=0.7, regression="ttfnet")
    data.setup("fit")
    assert len(data.train_set._cache) == 6 and len(data.val_set._cache) == 2
    for i in range(6):
        image, inside, _ = data.train_set._cache[i]
        assert np.array_equal(image, lazy.letterboxed(i)[0]) and np.array_equal(inside.boxes, lazy.letterboxed(i)[1].boxes)

    def no_decoding(*args):
        raise AssertionError("a loader process decoded an image")

    monkeypatch.setattr(dataset_module, "load_image", no_decoding)  # the forked processes inherit it
    batches = list(data.train_dataloader())
    assert sum(len(b["index"]) for b in batches) == 6
    assert sorted(torch.cat([b["index"] for b in batches]).tolist()) == list(range(6))
