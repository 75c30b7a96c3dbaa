"""Label Studio: the documented JSON export in, predictions out, the shipped labelling configuration."""

import json
import xml.etree.ElementTree as ET

import pytest

from deepword.labelling import CLASS_LABELS, LINK_LABELS, LabellingError, import_labels, label_studio_config
from deepword.labelling.label_studio import to_label_studio
from deepword.word_format import read_records
from tests.deepword.labelling.helpers import H, W, png, same_records, word_dataset, word_record


def region(rid, label, x, y, w, h, width=W, height=H, **value):
    return {"id": rid, "type": "rectanglelabels", "from_name": "label", "to_name": "image", "original_width": width,
            "original_height": height, "image_rotation": 0,
            "value": {"x": x, "y": y, "width": w, "height": h, "rotation": 0, "rectanglelabels": [label], **value}}


def relation(a, b, *labels):
    return {"type": "relation", "from_id": a, "to_id": b, "direction": "right", "labels": list(labels)}


def task(tid, image, results, **data):
    return {"id": tid, "data": {"image": image, **data},
            "annotations": [{"id": 100 + tid, "was_cancelled": False, "result": results}]}


def export(tmp_path, tasks):
    path = tmp_path / "export.json"
    path.write_text(json.dumps(tasks))
    return path


def good_tasks():
    """A car with its rear and front wheel; a second image with an unowned wheel, uploaded through Label Studio
    (its upload prefix on the name) and annotated twice (the first cancelled)."""
    t1 = task(12, "/data/local-files/?d=shots/cam_a.png", [
        region("car", "vehicle", 10, 20, 50, 50),
        region("r", "wheel", 12.5, 62.5, 10, 8),
        region("f", "wheel", 45, 62.5, 10, 8),
        relation("r", "car", "rear"), relation("f", "car", "front")], camera="left", frame_id=7)
    t2 = task(13, "/data/upload/3/8f3a2b1c-cam_b.png", [region("w", "wheel", 0, 0, 10, 10)])
    t2["annotations"].insert(0, {"id": 1, "was_cancelled": True, "result": []})
    t3 = {"id": 14, "data": {"image": "cam_c.png"}, "annotations": []}
    return [t1, t2, t3]


def test_the_shipped_configuration_has_exactly_the_labels_the_importer_accepts():
    view = ET.fromstring(label_studio_config())
    boxes = {el.get("value") for el in view.iter("Label")}
    relations = {el.get("value") for el in view.iter("Relation")}
    assert boxes == set(CLASS_LABELS)
    assert relations == set(LINK_LABELS)
    assert view.find("RectangleLabels").get("toName") == view.find("Image").get("name")


def test_a_label_studio_export_becomes_a_validated_dataset(tmp_path):
    png(tmp_path / "imgs" / "shots" / "cam_a.png")
    png(tmp_path / "imgs" / "cam_b.png")
    result = import_labels("label-studio", export(tmp_path, good_tasks()), tmp_path / "imgs", tmp_path / "ds")
    recs = {r.image: r for r in read_records(tmp_path / "ds" / "labels.jsonl", check_images=True)}
    a, b = recs["images/left/cam_a.png"], recs["images/front/cam_b.png"]
    assert (a.camera, a.frame_id, b.frame_id) == ("left", 7, 1)  # b: no frame field, no digits: its index
    assert a.boxes[:, :4].tolist()[0] == pytest.approx([6.4, 9.6, 38.4, 33.6])
    assert sorted(a.relations) == [(0, 1, "rear"), (0, 2, "front")]
    assert a.wheel_pairs == [(1, 2)]  # the roles give the couple
    assert b.n_wheels == 1 and b.relations == []
    s = result.summary
    assert (s.images, s.vehicles, s.wheels, s.owned, s.unowned, s.couples) == (2, 1, 3, 2, 1, 1)
    text = "\n".join(s.lines())
    assert "task 14" in text and "task 13" in text  # skipped, and the one with two annotations


def test_word_to_label_studio_and_back_is_the_identity(tmp_path):
    recs = [word_record(42, "front"), word_record(42, "rear"), word_record(43, "left")]
    word_dataset(tmp_path / "src", recs)
    tasks, notes = to_label_studio(recs, "m1")
    assert notes == []
    for t in tasks:  # the team accepts every pre-annotation as it is
        t["annotations"] = [{"id": 1, "result": t.pop("predictions")[0]["result"]}]
    import_labels("label-studio", export(tmp_path, tasks), tmp_path / "src", tmp_path / "ds")
    same_records(recs, read_records(tmp_path / "ds" / "labels.jsonl", check_images=True))


def test_predictions_carry_scores_and_the_model_version(tmp_path):
    rec = word_record()
    rec.boxes[:, 4] = 0.5
    (t,), _ = to_label_studio([rec], "detector-v2", "/data/local-files/?d=set/")
    assert t["data"]["image"] == "/data/local-files/?d=set/images/front/000042.png"
    pred = t["predictions"][0]
    assert pred["model_version"] == "detector-v2" and pred["score"] == 0.5
    regions = [r for r in pred["result"] if r["type"] == "rectanglelabels"]
    assert len(regions) == 10 and all(r["score"] == 0.5 for r in regions)
    couples = [r for r in pred["result"] if r.get("labels") == ["couple"]]
    assert {(r["from_id"], r["to_id"]) for r in couples} == {("4", "6"), ("5", "7")}  # vehicle 0's comes from roles


BAD = [
    ("outside", [region("a", "vehicle", 90, 10, 20, 10)], "task 1, region 'a': field 'value.width': box outside the image"),
    ("label", [region("a", "bicycle", 10, 10, 20, 10)], "task 1, region 'a': field 'value.rectanglelabels': unknown label 'bicycle'"),
    ("two owners", [region("v", "vehicle", 0, 0, 50, 50), region("u", "vehicle", 50, 0, 50, 50),
                    region("w", "wheel", 40, 40, 10, 10), relation("w", "v", "rear"), relation("w", "u", "front")],
     "task 1, relation 'w' -> 'u': field 'to_id': wheel 'w' has two owners"),
    ("two wheels", [region("a", "wheel", 0, 0, 10, 10), region("b", "wheel", 20, 0, 10, 10), relation("a", "b", "front")],
     "task 1, relation 'a' -> 'b': field 'to_id': relation between two wheels"),
    ("two vehicles", [region("a", "vehicle", 0, 0, 10, 10), region("b", "vehicle", 20, 0, 10, 10), relation("a", "b")],
     "task 1, relation 'a' -> 'b': field 'to_id': relation between two vehicles"),
    ("missing id", [region("a", "wheel", 0, 0, 10, 10), relation("a", "gone", "rear")],
     "task 1, relation 'a' -> 'gone': field 'to_id': relation to a missing id 'gone'"),
    ("size", [region("a", "wheel", 0, 0, 10, 10, width=640, height=480)],
     "task 1: field 'original_width': the export says 640x480, the image file img.png is 64x48"),
    ("rotated", [region("a", "wheel", 0, 0, 10, 10, rotation=30)], "task 1, region 'a': field 'value.rotation': rotated"),
]


@pytest.mark.parametrize("results, expected", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_each_bad_input_is_one_line_naming_element_and_field(tmp_path, results, expected):
    png(tmp_path / "imgs" / "img.png")
    with pytest.raises(LabellingError) as err:
        import_labels("label-studio", export(tmp_path, [task(1, "img.png", results)]), tmp_path / "imgs",
                      tmp_path / "ds")
    assert err.value.count == 1, err.value.all_lines
    assert err.value.all_lines[0].startswith("export.json: " + expected), err.value.all_lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export.json", "imgs"]  # nothing written, no temp left


def test_every_problem_is_reported_and_nothing_is_written(tmp_path):
    png(tmp_path / "imgs" / "img.png")
    tasks = [task(1, "img.png", [region("a", "car", 0, 0, 10, 10)]),
             task(2, "nowhere.png", [region("b", "wheel", 0, 0, 10, 10)]),
             task(3, "img.png", [region("c", "wheel", -20, 0, 10, 10)], camera="roof")]
    with pytest.raises(LabellingError) as err:
        import_labels("label-studio", export(tmp_path, tasks), tmp_path / "imgs", tmp_path / "ds")
    lines = err.value.all_lines
    assert any("task 1, region 'a': field 'value.rectanglelabels': unknown label 'car'" in x for x in lines)
    assert any("task 2: field 'data.image': image file 'nowhere.png' not found" in x for x in lines)
    assert any("task 3: field 'camera': must be one of" in x for x in lines)
    assert not (tmp_path / "ds").exists()


def test_a_box_overshooting_by_rounding_is_clipped(tmp_path):
    png(tmp_path / "imgs" / "img.png")
    path = export(tmp_path, [task(1, "img.png", [region("a", "wheel", -1.0, 50, 101.5, 50)])])
    import_labels("label-studio", path, tmp_path / "imgs", tmp_path / "ds")
    (rec,) = read_records(tmp_path / "ds" / "labels.jsonl")
    assert rec.boxes[0, :4].tolist() == [0.0, 24.0, 64.0, 48.0]
