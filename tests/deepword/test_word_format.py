"""The dataset format's public API (docs/design.md §4, §7): records in and out, field-by-field validation,
image headers, the split policy and the data stage's index. (Every bad input of the reliability corpus is
tried in tests/reliability; here each part on its own.)"""

import json

import cv2
import numpy as np
import pytest

from deepword.word_format import (
    DatasetError,
    Record,
    boxes_only,
    difficulty_subsets,
    image_size,
    open_dataset,
    parse_record,
    read_records,
    split_by_frame,
    write_dataset_index,
    write_records,
)

GOOD = {"image": "images/front/1.png", "frame_id": 1, "camera": "front", "scene": "parking", "width": 64,
        "height": 48, "boxes": [[2, 10, 40, 40, 1.0, 0, 0], [5, 30, 13, 40, 1.0, 1, 1], [30, 30, 38, 40, 1.0, 1, 2]],
        "relations": [[0, 1, "rear"], [0, 2]], "wheel_pairs": [[1, 2]], "weather": "rain"}


def test_a_record_parses_writes_and_reads_back_unchanged(tmp_path):
    rec = parse_record(GOOD, "labels.jsonl", 1)
    assert rec.n_vehicles == 1 and rec.n_wheels == 2 and rec.owner_of() == {1: 0, 2: 0}
    assert rec.relations == [(0, 1, "rear"), (0, 2, None)] and rec.wheel_pairs == [(1, 2)]
    assert rec.extra == {"weather": "rain"}  # unknown keys are kept
    write_records(tmp_path / "labels.jsonl", [rec])
    (back,) = read_records(tmp_path / "labels.jsonl")
    assert back.to_json() == rec.to_json() == {**GOOD, "boxes": [[float(v) if i < 5 else v for i, v in enumerate(b)]
                                                                  for b in GOOD["boxes"]]}
    assert back.source == (str(tmp_path / "labels.jsonl"), 1)
    bare = boxes_only(back)
    assert bare.relations == [] and bare.wheel_pairs == [] and np.array_equal(bare.boxes, back.boxes)
    assert bare.boxes is not back.boxes
    assert "ignore" not in rec.to_json() and rec.ignore.shape == (0, 5)  # optional, and not written when empty


def test_ignore_regions_parse_write_back_and_stay_out_of_what_methods_see(tmp_path):
    rec = parse_record({**GOOD, "ignore": [[40, 5, 60, 20, 0], [50, 30, 53, 36, 1]]}, "labels.jsonl", 1)
    assert rec.ignore.tolist() == [[40, 5, 60, 20, 0], [50, 30, 53, 36, 1]]
    assert "ignore" not in rec.extra
    write_records(tmp_path / "labels.jsonl", [rec])
    (back,) = read_records(tmp_path / "labels.jsonl")
    assert back.to_json()["ignore"] == [[40.0, 5.0, 60.0, 20.0, 0], [50.0, 30.0, 53.0, 36.0, 1]]
    assert boxes_only(back).ignore.shape == (0, 5)


@pytest.mark.parametrize(("change", "field", "message"), [
    ({"image": "../x.png"}, "image", "leaves the dataset root"),
    ({"camera": "roof"}, "camera", "must be one of"),
    ({"width": 0}, "width", "positive integer"),
    ({"boxes": [[40, 10, 2, 40, 1.0, 0, 0]]}, "boxes[0]", "x1 < x2 required"),
    ({"boxes": [[2, 10, 40, 40, 1.0, 0, 0], [5, 30, 13, 40, 1.0, 1, 0]]}, "boxes[1]", "duplicate box_id 0"),
    ({"relations": [[1, 0]]}, "relations[0]", "is not a vehicle"),
    ({"relations": [[0, 1], [0, 1]]}, "relations[1]", "already has owner 0"),
    ({"wheel_pairs": [[1, 1]]}, "wheel_pairs[0]", "cannot pair with itself"),
    ({"ignore": {"x": 1}}, "ignore", "must be a list"),
    ({"ignore": [[1, 2, 3, 4]]}, "ignore[0]", r"must be \[x1, y1, x2, y2, class_id\]"),
    ({"ignore": [[10, 2, 3, 4, 0]]}, "ignore[0]", "x1 < x2 and y1 < y2 required"),
    ({"ignore": [[1, 2, 3, 4, 0], [1, 2, 90, 4, 1]]}, "ignore[1]", "outside the 64x48 image"),
    ({"ignore": [[1, 2, 3, 4, 7]]}, "ignore[0]", "unknown class_id 7"),
])
def test_each_field_is_checked_and_named_with_file_and_line(change, field, message):
    with pytest.raises(DatasetError, match=message) as err:
        parse_record({**GOOD, **change}, "labels.jsonl", 7)
    assert (err.value.file, err.value.line, err.value.field) == ("labels.jsonl", 7, field)
    assert str(err.value).startswith(f"labels.jsonl:7: field '{field}': ")


def test_image_size_reads_png_and_jpeg_headers_and_refuses_truncated_files(tmp_path):
    rgb = np.zeros((48, 64, 3), np.uint8)
    for ext in ("png", "jpg"):
        path = tmp_path / f"a.{ext}"
        cv2.imwrite(str(path), rgb)
        assert image_size(path) == (64, 48)
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(ValueError, match="truncated"):
            image_size(path)
    (tmp_path / "x.gif").write_bytes(b"GIF89a" + bytes(30))
    with pytest.raises(ValueError, match="not a PNG or JPEG"):
        image_size(tmp_path / "x.gif")


def _record(frame: int, camera: str, vehicles: int) -> Record:
    boxes = np.array([[i * 10, 0, i * 10 + 8, 8, 1.0, 0, i] for i in range(vehicles)], dtype=float).reshape(-1, 7)
    return Record(image=f"{camera}/{frame}.png", frame_id=frame, camera=camera, width=64, height=48, boxes=boxes,
                  relations=[], wheel_pairs=[])


def test_splits_keep_a_frames_cameras_together_and_subsets_follow_the_vehicle_count():
    records = [_record(f, c, (f % 6) + 1) for f in range(40) for c in ("front", "left", "right", "rear")]
    splits = split_by_frame(records, {"train": 0.7, "val": 0.1, "test": 0.2}, seed=3)
    assert splits == split_by_frame(records, {"train": 0.7, "val": 0.1, "test": 0.2}, seed=3)  # seeded
    frame_of = {r.image: r.frame_id for r in records}
    frames = {s: {frame_of[i] for i in images} for s, images in splits.items()}
    assert not (frames["train"] & frames["val"]) and not (frames["train"] & frames["test"])
    assert sum(map(len, splits.values())) == len(records) and len(frames["test"]) == 8
    test = [r for r in records if r.image in set(splits["test"])]
    subsets = difficulty_subsets(test, seed=0, max_easy_vehicles=3)
    by_image = {r.image: r for r in test}
    assert all(by_image[i].n_vehicles <= 3 for i in subsets["easy"])
    assert all(by_image[i].n_vehicles > 3 for i in subsets["hard"])
    mixed = subsets["mixed"]
    assert len(mixed) % 2 == 0 and sum(i in subsets["easy"] for i in mixed) == len(mixed) // 2


def test_the_data_stage_index_opens_as_a_dataset(tmp_path):
    root = tmp_path / "data"
    (root / "images" / "front").mkdir(parents=True)
    cv2.imwrite(str(root / GOOD["image"]), np.zeros((48, 64, 3), np.uint8))
    write_records(root / "labels.jsonl", [parse_record(GOOD, "labels.jsonl", 1)])
    write_dataset_index(root, root, {"train": [GOOD["image"]], "val": [], "test": []})
    assert json.loads((root / "dataset.json").read_text())["root"] == "."
    ds = open_dataset(root)
    assert [r.image for r in ds.subset("train")] == [GOOD["image"]] and ds.subset("val") == []
    with pytest.raises(KeyError, match="unknown split 'easy'"):
        ds.subset("easy")
    with pytest.raises(DatasetError, match="not a data stage output"):
        open_dataset(tmp_path)
