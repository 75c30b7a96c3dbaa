"""CVAT for images 1.1 XML and COCO detection JSON, written as their documentation describes them."""

import json

import pytest

from deepword.labelling import LabellingError, import_labels, to_cvat
from deepword.word_format import read_records
from tests.deepword.labelling.helpers import png, same_records, word_dataset, word_record


def cvat_file(tmp_path, boxes, name="frame.png", width=64, height=48):
    xml = f"""<?xml version="1.0" encoding="utf-8"?>
<annotations><version>1.1</version>
  <image id="0" name="{name}" width="{width}" height="{height}">{boxes}</image>
</annotations>"""
    path = tmp_path / "annotations.xml"
    path.write_text(xml)
    return path


def box(label, xtl, ytl, xbr, ybr, group=None, role=None, couple=None):
    group_attr = f' group_id="{group}"' if group is not None else ""
    attrs = "".join(f'<attribute name="{n}">{v}</attribute>' for n, v in (("role", role), ("couple", couple)) if v)
    return (f'<box label="{label}" occluded="0" source="manual" xtl="{xtl}" ytl="{ytl}" xbr="{xbr}" ybr="{ybr}" '
            f'z_order="0"{group_attr}>{attrs}</box>')


def test_a_cvat_export_becomes_a_validated_dataset(tmp_path):
    png(tmp_path / "imgs" / "frame.png")
    boxes = (box("vehicle", 2, 10, 30, 40, group=1) + box("wheel", 4, 30, 10, 38, group=1, role="rear")
             + box("wheel", 22, 30, 28, 38, group=1, role="front") + box("wheel", 40, 30, 44, 38))
    result = import_labels("cvat", cvat_file(tmp_path, boxes), tmp_path / "imgs", tmp_path / "ds", camera="right")
    (rec,) = read_records(tmp_path / "ds" / "labels.jsonl", check_images=True)
    assert rec.image == "images/right/frame.png" and rec.frame_id == 0
    assert sorted(rec.relations) == [(0, 1, "rear"), (0, 2, "front")] and rec.wheel_pairs == [(1, 2)]
    assert (result.summary.owned, result.summary.unowned) == (2, 1)


def test_word_to_cvat_and_back_is_the_identity(tmp_path):
    recs = [word_record(42, "front"), word_record(42, "left")]
    word_dataset(tmp_path / "src", recs)
    xml, notes = to_cvat(recs)
    assert notes == []
    (tmp_path / "annotations.xml").write_text(xml)
    import_labels("cvat", tmp_path / "annotations.xml", tmp_path / "src", tmp_path / "ds")
    same_records(recs, read_records(tmp_path / "ds" / "labels.jsonl", check_images=True))


CVAT_BAD = [
    ("two vehicles", box("vehicle", 0, 0, 20, 20, group=2) + box("vehicle", 30, 0, 50, 20, group=2)
     + box("wheel", 5, 10, 9, 19, group=2), "image 'frame.png', box 0 (vehicle): field 'group_id': group 2 has 2 vehicles"),
    ("no vehicle", box("wheel", 5, 10, 9, 19, group=4), "image 'frame.png', box 0 (wheel): field 'group_id': group 4 has no vehicle"),
    ("outside", box("wheel", 60, 10, 70, 19), "image 'frame.png', box 0 (wheel): field 'xbr': box outside the image"),
    ("label", box("truck", 0, 0, 20, 20), "image 'frame.png', box 0 (truck): field 'label': unknown label 'truck'"),
    ("role", box("vehicle", 0, 0, 20, 20, group=1) + box("wheel", 5, 10, 9, 19, group=1, role="middle"),
     "image 'frame.png', box 1 (wheel): field 'attribute 'role'': unknown role 'middle'"),
    ("couple", box("vehicle", 0, 0, 20, 20, group=1) + box("wheel", 5, 10, 9, 19, group=1, role="rear", couple=1),
     "image 'frame.png', box 1 (wheel): field 'attribute 'couple'': couple 1 has 1 wheels"),
    ("polygon", '<polygon label="wheel" points="1,1;5,5;1,5"/>', "image 'frame.png', <polygon> #1: field '<shape>'"),
]


@pytest.mark.parametrize("boxes, expected", [b[1:] for b in CVAT_BAD], ids=[b[0] for b in CVAT_BAD])
def test_each_bad_cvat_input_is_one_line(tmp_path, boxes, expected):
    png(tmp_path / "imgs" / "frame.png")
    with pytest.raises(LabellingError) as err:
        import_labels("cvat", cvat_file(tmp_path, boxes), tmp_path / "imgs", tmp_path / "ds")
    assert err.value.count == 1, err.value.all_lines
    assert err.value.all_lines[0].startswith("annotations.xml: " + expected), err.value.all_lines[0]
    assert not (tmp_path / "ds").exists()


def test_cvat_image_size_must_match_the_file(tmp_path):
    png(tmp_path / "imgs" / "frame.png")
    with pytest.raises(LabellingError, match=r"image 'frame.png': field 'width': the export says 640x48"):
        import_labels("cvat", cvat_file(tmp_path, "", width=640), tmp_path / "imgs", tmp_path / "ds")


def coco_file(tmp_path, annotations, images=None):
    doc = {"images": images or [{"id": 5, "file_name": "000009.png", "width": 64, "height": 48, "camera": "rear"}],
           "categories": [{"id": 1, "name": "vehicle"}, {"id": 2, "name": "wheel"}],
           "annotations": annotations}
    path = tmp_path / "instances.json"
    path.write_text(json.dumps(doc))
    return path


def ann(aid, cat, bbox, **extra):
    return {"id": aid, "image_id": 5, "category_id": cat, "bbox": bbox, "area": bbox[2] * bbox[3], "iscrowd": 0,
            **extra}


def test_a_coco_file_becomes_a_validated_dataset(tmp_path):
    png(tmp_path / "imgs" / "000009.png")
    anns = [ann(10, 1, [2, 10, 28, 30]),
            ann(11, 2, [4, 30, 6, 8], attributes={"owner": 10, "role": "rear", "occluded": False}),
            ann(12, 2, [22, 30, 6, 8], owner=10, role="front"),  # the top-level form
            ann(13, 2, [40, 30, 4, 8], attributes={"owner": 0, "role": ""}),  # CVAT's default: no owner
            {**ann(14, 2, [50, 30, 4, 8]), "iscrowd": 1}]
    result = import_labels("coco", coco_file(tmp_path, anns), tmp_path / "imgs", tmp_path / "ds")
    (rec,) = read_records(tmp_path / "ds" / "labels.jsonl", check_images=True)
    assert (rec.image, rec.camera, rec.frame_id) == ("images/rear/000009.png", "rear", 9)
    assert sorted(rec.relations) == [(10, 11, "rear"), (10, 12, "front")] and rec.wheel_pairs == [(11, 12)]
    assert rec.ignore.tolist() == [[50, 30, 54, 38, 1]]
    assert (result.summary.wheels, result.summary.unowned) == (3, 1)


COCO_BAD = [
    ("missing owner", [ann(11, 2, [4, 30, 6, 8], attributes={"owner": 99})],
     "image '000009.png', annotation 11: field 'attributes.owner': relation to a missing id '99'"),
    ("owner is a wheel", [ann(11, 2, [4, 30, 6, 8]), ann(12, 2, [20, 30, 6, 8], owner=11)],
     "image '000009.png', annotation 12: field 'owner': relation between two wheels"),
    ("category", [ann(11, 7, [4, 30, 6, 8])], "image '000009.png', annotation 11: field 'category_id': unknown category_id 7"),
    ("outside", [ann(11, 2, [-5, 30, 6, 8])], "image '000009.png', annotation 11: field 'bbox[0]': box outside the image"),
]


@pytest.mark.parametrize("anns, expected", [b[1:] for b in COCO_BAD], ids=[b[0] for b in COCO_BAD])
def test_each_bad_coco_input_is_one_line(tmp_path, anns, expected):
    png(tmp_path / "imgs" / "000009.png")
    with pytest.raises(LabellingError) as err:
        import_labels("coco", coco_file(tmp_path, anns), tmp_path / "imgs", tmp_path / "ds")
    assert err.value.count == 1, err.value.all_lines
    assert err.value.all_lines[0].startswith("instances.json: " + expected), err.value.all_lines[0]
