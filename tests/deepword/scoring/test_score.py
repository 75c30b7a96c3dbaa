"""The scoring CLI on a tiny dataset: perfect and partial predictions, missing and unknown images,
malformed predictions files."""

import json
from dataclasses import replace

import pytest

from deepword.scoring.score import main
from deepword.word_format import read_records, write_records
from tests.deepword.tiny_word import build


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return build(tmp_path_factory.mktemp("score") / "data", n_train=10, n_test=10, seed=3)


def test_ground_truth_as_predictions_scores_100(data, tmp_path, capsys):
    out = tmp_path / "scores.json"
    assert main(["--gt", str(data), "--pred", str(data / "labels.jsonl"), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| wheel_acc (%) | easy | hard | mixed |" in printed and "*71.83*" in printed
    res = json.loads(out.read_text())
    assert res["missing_images"] == 0
    for subset in ("easy", "hard", "mixed"):
        assert all(v == 100.0 for v in res["results"][subset].values())
        assert all(v == 100.0 for v in res["relation_oracle"][subset].values())  # the boxes cost nothing
    assert "| relation_oracle |" in printed
    assert res["sizes"]["easy"]["images"] + res["sizes"]["hard"]["images"] == 20
    # the tiny dataset labels no roles: none is scored, and the report says so
    assert res["roles"]["relations"] == 0 and "no predicted relation names a true one whose role" in printed


def test_an_empty_subset_says_so_instead_of_scoring_100(data, tmp_path, capsys):
    # every image has a vehicle, so with at most 0 vehicles an easy image there is none
    recs = read_records(data / "labels.jsonl")
    write_records(tmp_path / "pred.jsonl", [replace(r, relations=[], wheel_pairs=[]) for r in recs])
    out = tmp_path / "scores.json"
    assert main(["--gt", str(data), "--pred", str(tmp_path / "pred.jsonl"), "--json", str(out),
                 "--max-easy-vehicles", "0"]) == 0
    printed = capsys.readouterr().out
    assert "easy: no images" in printed
    assert "| submitted | - | 0.00 | 0.00 |" in printed and "| relation_oracle | - | 100.00 | 100.00 |" in printed
    res = json.loads(out.read_text())
    assert res["empty_subsets"] == ["easy"] and res["sizes"]["easy"] == {"images": 0, "wheels": 0}
    for key in ("results", "relation_oracle", "pair_errors"):
        assert "easy" not in res[key] and {"hard", "mixed"} <= set(res[key])
    assert res["results"]["hard"]["pair_f1"] == 0.0  # no relations predicted: the other subsets are scored as ever


def test_missing_images_count_as_no_relations(data, tmp_path):
    recs = read_records(data / "labels.jsonl")
    write_records(tmp_path / "pred.jsonl", recs[:5])
    out = tmp_path / "scores.json"
    assert main(["--gt", str(data), "--pred", str(tmp_path / "pred.jsonl"), "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["missing_images"] == 15
    assert res["results"]["mixed"]["pair_recall"] < 100


def test_pair_errors_are_printed_and_written(data, tmp_path, capsys):
    recs = read_records(data / "labels.jsonl")
    dropped = [replace(r, relations=r.relations[1:]) if r.relations else r for r in recs]  # one pair less an image
    write_records(tmp_path / "pred.jsonl", dropped)
    out = tmp_path / "scores.json"
    assert main(["--gt", str(data), "--pred", str(tmp_path / "pred.jsonl"), "--json", str(out), "--min-box-px", "0"]) == 0
    assert "## Where the pair errors are: predictions" in capsys.readouterr().out
    errors = json.loads(out.read_text())["pair_errors"]
    lost = sum(1 for r in recs if r.relations)
    # every box is there, so each dropped pair is "both detected, not paired" and nothing is claimed falsely
    assert errors["easy"]["not_paired"] + errors["hard"]["not_paired"] == lost
    assert all(errors[s][k] == 0 for s in errors for k in ("wheel_missed", "vehicle_missed", "false_wheel",
                                                           "false_vehicle", "wrong_pair"))
    # all boxes there: a perfect relation model would score 100, so the whole loss is the relations'
    ceiling = json.loads(out.read_text())["relation_oracle"]
    assert all(ceiling[s]["pair_f1"] == 100.0 for s in ceiling)


def test_detections_add_the_detectors_ap_and_where_it_goes(data, tmp_path, capsys):
    recs = read_records(data / "labels.jsonl")
    # every box found, but the first image's first box shrunk to a quarter (a loose box) and one image not detected
    loose = []
    for k, r in enumerate(recs[1:]):
        boxes = r.boxes.copy()
        boxes[:, 4] = 0.9
        if k == 0:
            x1, y1, x2, y2 = boxes[0, :4]
            boxes[0, 2:4] = (x1 + (x2 - x1) / 2, y1 + (y2 - y1) / 2)
        loose.append(replace(r, boxes=boxes, relations=[], wheel_pairs=[]))
    write_records(tmp_path / "detections.jsonl", loose)
    out = tmp_path / "scores.json"
    argv = ["--gt", str(data), "--pred", str(data / "labels.jsonl"), "--detections", str(tmp_path / "detections.jsonl"),
            "--json", str(out), "--min-box-px", "0"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "## Detector" in printed and "## Where AP@0.5 goes (whole dataset)" in printed
    detector = json.loads(out.read_text())["detector"]
    assert detector["missing_images"] == 1
    cls = "vehicle" if recs[1].boxes[0, 5] == 0 else "wheel"
    assert detector["breakdown"][cls]["n_loose"] == 1
    assert detector["breakdown"][cls]["ap50_loose_placed"] > detector["ap"][cls]["ap50"]
    assert all(0 < v["ap50"] < 100 for v in detector["ap"].values())   # the undetected image's boxes are missed


def test_detections_must_be_of_the_datasets_images(data, tmp_path, capsys):
    lines = (data / "labels.jsonl").read_text().splitlines()
    obj = json.loads(lines[0])
    obj["width"] += 1
    (tmp_path / "detections.jsonl").write_text(json.dumps(obj) + "\n")
    argv = ["--gt", str(data), "--pred", str(data / "labels.jsonl"), "--detections", str(tmp_path / "detections.jsonl")]
    assert main(argv) == 2
    assert "detections.jsonl:1: field 'width'" in capsys.readouterr().err


def test_unknown_image_is_an_error(data, tmp_path, capsys):
    lines = (data / "labels.jsonl").read_text().splitlines()
    obj = json.loads(lines[0])
    obj["image"] = "images/left/99999.png"
    (tmp_path / "pred.jsonl").write_text(lines[1] + "\n" + json.dumps(obj) + "\n")
    assert main(["--gt", str(data), "--pred", str(tmp_path / "pred.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "pred.jsonl:2" in err and "'image'" in err and "not an image of the ground-truth dataset" in err


def test_predictions_at_another_resolution_are_an_error(data, tmp_path, capsys):
    lines = (data / "labels.jsonl").read_text().splitlines()
    obj = json.loads(lines[1])
    obj["width"], obj["height"] = obj["width"] // 2, obj["height"] // 2
    obj["boxes"] = [[v / 2 if k < 4 else v for k, v in enumerate(b)] for b in obj["boxes"]]
    (tmp_path / "pred.jsonl").write_text(lines[0] + "\n" + json.dumps(obj) + "\n")
    assert main(["--gt", str(data), "--pred", str(tmp_path / "pred.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "pred.jsonl:2" in err and "'width'" in err and "boxes must be in the ground-truth image's pixels" in err


@pytest.mark.parametrize("mutate, where", [
    (lambda o: "{not json", ":1: field '<json>'"),
    (lambda o: json.dumps({**o, "boxes": [[5, 5, 1, 9, 0.5, 0, 0]]}), ":1: field 'boxes[0]'"),
    (lambda o: json.dumps({**o, "relations": [[0, 999]]}), ":1: field 'relations[0]'"),
    (lambda o: json.dumps({k: v for k, v in o.items() if k != "width"}), ":1: field 'width'"),
])
def test_malformed_predictions_exit_2_with_file_line_field(data, tmp_path, capsys, mutate, where):
    obj = json.loads((data / "labels.jsonl").read_text().splitlines()[0])
    (tmp_path / "pred.jsonl").write_text(mutate(obj) + "\n")
    assert main(["--gt", str(data), "--pred", str(tmp_path / "pred.jsonl")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and where in err and "Traceback" not in err


def test_missing_files_are_clear_errors(data, tmp_path, capsys):
    assert main(["--gt", str(data), "--pred", str(tmp_path / "nope.jsonl")]) == 2
    assert "predictions file not found" in capsys.readouterr().err
    assert main(["--gt", str(tmp_path), "--pred", str(data / "labels.jsonl")]) == 2
    assert "not a WORD-style dataset" in capsys.readouterr().err


def test_cli_as_a_module_has_no_traceback(data, tmp_path):
    import subprocess
    import sys

    (tmp_path / "pred.jsonl").write_text("[1, 2]\n")
    proc = subprocess.run([sys.executable, "-m", "deepword.scoring.score", "--gt", str(data), "--pred",
                           str(tmp_path / "pred.jsonl")], capture_output=True, text=True)
    assert proc.returncode == 2 and "pred.jsonl:1" in proc.stderr and "Traceback" not in proc.stderr
