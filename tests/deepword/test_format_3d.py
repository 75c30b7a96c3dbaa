"""The optional calibration and objects_3d keys: validated by the reader with file:line:field errors,
optional for 2D datasets."""

import json

import pytest

from deepword.word_format import DatasetError, read_records

RECORD = {"image": "images/front/000000.png", "frame_id": 0, "camera": "front", "width": 640, "height": 480,
          "boxes": [[10, 10, 60, 40, 1.0, 0, 0], [20, 30, 30, 40, 1.0, 1, 1]], "relations": [[0, 1, "rear"]]}
CALIBRATION = {"intrinsic": {"model": "radial_poly", "k1": 170.0, "k2": -16.0, "k3": 24.0, "k4": -3.6,
                             "cx_offset": 2.0, "cy_offset": -1.5, "aspect_ratio": 1.0, "width": 640, "height": 480},
               "extrinsic": {"quaternion": [0.594, -0.588, 0.387, -0.389], "translation": [3.75, 0.0, 0.66]}}
OBJECTS = {"0": {"center": [6.0, 1.0, 0.75], "size": [4.5, 1.8, 1.5], "yaw": 0.1}, "1": {"contact": [4.9, 0.2]}}


def _read(tmp_path, **changes):
    rec = json.loads(json.dumps({**RECORD, "image": "images/front/000001.png", "calibration": CALIBRATION,
                                 "objects_3d": OBJECTS}))
    for path, value in changes.items():
        *keys, last = path.split("__")
        node = rec
        for k in keys:
            node = node[k]
        if value is None:
            del node[last]
        else:
            node[last] = value
    (tmp_path / "labels.jsonl").write_text(json.dumps(RECORD) + "\n" + json.dumps(rec) + "\n")
    return read_records(tmp_path / "labels.jsonl")


def test_a_complete_record_and_a_plain_2d_record_both_read(tmp_path):
    plain, full = _read(tmp_path)
    assert "calibration" not in plain.extra and full.extra["calibration"]["intrinsic"]["model"] == "radial_poly"


def test_the_ego_body_reads_into_the_camera_and_writes_back(tmp_path):
    from deepword.format_3d import record_camera

    body = [[[0.0, 440.0], [640.0, 440.0], [640.0, 480.0], [0.0, 480.0]]]
    _, rec = _read(tmp_path, calibration__ego_body=body)
    cam = record_camera(rec, "test")
    assert cam.calibration()["ego_body"] == body
    assert cam.ego_mask[440:].all() and not cam.ego_mask[:439].any()
    assert record_camera(_read(tmp_path)[1], "test").ego_mask is None


@pytest.mark.parametrize("change, field, message", [
    ({"calibration__intrinsic__model": "pinhole"}, "calibration.intrinsic.model", "must be one of"),
    ({"calibration__intrinsic__k3": None}, "calibration.intrinsic.k3", "missing"),
    ({"calibration__intrinsic__width": 1280}, "calibration.intrinsic.width", "the image is 640x480"),
    ({"calibration__extrinsic__quaternion": [0, 0, 1]}, "calibration.extrinsic.quaternion", "[qx, qy, qz, qw]"),
    ({"calibration__extrinsic__quaternion": [0, 0, 0, 0.01]}, "calibration.extrinsic.quaternion", "not a rotation"),
    ({"calibration__intrinsic__k1": -5.0}, "calibration.intrinsic.k1", "must be positive"),
    ({"calibration__ego_body": {"front": []}}, "calibration.ego_body", "must be a list of polygons"),
    ({"calibration__ego_body": [[[0, 470], [640, 470]]]}, "calibration.ego_body[0]", "at least three"),
    ({"calibration__ego_body": [[[0, 470], [640, 470], [640]]]}, "calibration.ego_body[0][2]", "[x, y]"),
    ({"calibration__ego_body": [[[0, 470], [700, 470], [640, 480]]]}, "calibration.ego_body[0][1]",
     "outside the 640x480 image"),
    ({"objects_3d__7": {"contact": [1, 2]}}, "objects_3d.7", "box_id 7 does not exist"),
    ({"objects_3d__0__size": [4.5, 0, 1.5]}, "objects_3d.0.size", "> 0"),
    ({"objects_3d__1": {"center": [1, 2, 0]}}, "objects_3d.1.contact", "ground contact"),
])
def test_bad_3d_keys_are_named_by_file_line_and_field(tmp_path, change, field, message):
    with pytest.raises(DatasetError) as err:
        _read(tmp_path, **change)
    assert err.value.line == 2 and err.value.field == field and message in err.value.message
