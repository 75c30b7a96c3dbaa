"""The scoring path: a detector predictions file with problems is refused with file, line and field,
never scored silently (docs/design.md §4: predictions use the dataset format with real scores)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from deepword.word_format import Dataset as WordDataset
from deepword.word_format import DatasetError, read_records
from stages.evaluate.methods import EvalContext, detected_boxes
from tests.reliability.make_corpus import Dataset, write_dataset
from tests.stage_inputs import stage_inputs


def context(tmp_path: Path, prediction_lines: list[str]) -> EvalContext:
    root = write_dataset(Dataset(), tmp_path / "data")
    records = read_records(root / "labels.jsonl")
    detector = tmp_path / "detector"
    detector.mkdir()
    inputs = stage_inputs("evaluate", {"detector": detector})
    inputs.output("detector", "predictions", split="test").write_text("".join(line + "\n" for line in prediction_lines))
    ds = WordDataset(root=root, records=records, splits={"test": [r.image for r in records]})
    return EvalContext(cfg=OmegaConf.create({}), seed=0, inputs=inputs, dataset=ds, priors=None)


def prediction(**changes) -> str:
    rec = Dataset().records[0]
    rec["boxes"] = [[1, 1, 15, 11, 0.9, 0, 0], [2, 8, 5, 11, 0.7, 1, 1]]
    rec["relations"], rec["wheel_pairs"] = [], []
    rec.update(changes)
    return json.dumps(rec)


def test_valid_predictions_file_is_read_for_scoring(tmp_path):
    boxes = detected_boxes(context(tmp_path, [prediction()]))
    assert list(boxes) == ["images/front/000000.png"] and boxes["images/front/000000.png"].boxes.shape == (2, 7)


def test_empty_predictions_file_means_no_detections_not_an_error(tmp_path):
    assert detected_boxes(context(tmp_path, [])) == {}


@pytest.mark.parametrize("bad_line, field, message", [
    (prediction()[:-5], "<json>", "malformed JSON"),
    (prediction(boxes=[[1, 1, 15, 11, 1.5, 0, 0]]), "boxes[0]", "score must be in [0, 1]"),
    (prediction(boxes=[[1, 1, 15, 11, float("nan"), 0, 0]]), "boxes[0]", "finite"),
    (prediction(boxes=[[9, 1, 3, 11, 0.5, 0, 0]]), "boxes[0]", "x1 < x2"),
    (prediction(image="../../elsewhere/000000.png"), "image", "leaves the dataset root"),
    (prediction(relations=[[1, 0]]), "relations[0]", "not a vehicle"),
])
def test_bad_prediction_line_is_refused_naming_file_line_and_field(tmp_path, bad_line, field, message):
    ctx = context(tmp_path, [prediction(image="images/left/000001.png", frame_id=1, camera="left"), bad_line])
    with pytest.raises(DatasetError) as info:
        detected_boxes(ctx)
    err = info.value
    assert err.file.endswith("predictions_test.jsonl") and err.line == 2 and err.field == field
    assert message in err.message


@pytest.mark.parametrize("bad_line, field, message", [
    (prediction()[:-5], "<json>", "malformed JSON"),
    (prediction(boxes=[[1, 1, 15, 11, 1.5, 0, 0]]), "boxes[0]", "score must be in [0, 1]"),
    (prediction(image="images/rear/000099.png"), "image", "not an image of the ground-truth dataset"),
])
def test_score_command_refuses_bad_predictions_with_exit_2_and_location(tmp_path, capsys, bad_line, field, message):
    from deepword.scoring.score import main as score_main

    root = write_dataset(Dataset(), tmp_path / "data")
    pred = tmp_path / "pred.jsonl"
    pred.write_text(prediction() + "\n" + bad_line + "\n")
    assert score_main(["--gt", str(root), "--pred", str(pred)]) == 2
    err = capsys.readouterr().err
    assert f"pred.jsonl:2: field '{field}'" in err and message in err and "Traceback" not in err
