"""``deepword import`` and ``deepword export-labels`` end to end, and the package's place on the torch-free side."""

import json
import subprocess
import sys
from pathlib import Path

from deepword.word_format import read_records
from stages.cli import main
from tests.deepword.labelling.helpers import word_dataset, word_record

REPO = Path(__file__).resolve().parents[3]


def test_export_then_import_through_the_command_line(tmp_path, capsys):
    recs = [word_record(42, "front"), word_record(43, "front")]
    labels = word_dataset(tmp_path / "pred", recs)
    assert main(["export-labels", "--to", "label-studio", "--pred", str(labels), "--out", str(tmp_path / "ls.json"),
                 "--model-version", "v7"]) == 0
    assert "wrote 2 images' predictions for label-studio" in capsys.readouterr().out
    tasks = json.loads((tmp_path / "ls.json").read_text())
    assert tasks[0]["predictions"][0]["model_version"] == "v7"
    for t in tasks:
        t["annotations"] = [{"id": 1, "result": t["predictions"][0]["result"]}]
    (tmp_path / "ls.json").write_text(json.dumps(tasks))
    code = main(["import", "--from", "label-studio", str(tmp_path / "ls.json"), "--images", str(tmp_path / "pred"),
                 "--out", str(tmp_path / "ds"), "--link"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "images:   2" in out and "wheels:   16 (14 owned, 2 without a vehicle" in out and "6 wheel pairs" in out
    assert len(read_records(tmp_path / "ds" / "labels.jsonl", check_images=True)) == 2

    assert main(["export-labels", "--to", "cvat", "--pred", str(labels), "--out", str(tmp_path / "a.xml")]) == 0
    assert main(["import", "--from", "cvat", str(tmp_path / "a.xml"), "--images", str(tmp_path / "pred"),
                 "--out", str(tmp_path / "ds2")]) == 0


def test_problems_exit_2_with_one_line_each(tmp_path, capsys):
    (tmp_path / "imgs").mkdir()
    (tmp_path / "e.json").write_text(json.dumps([{"id": 3, "data": {"image": "x.png"},
                                                  "annotations": [{"result": []}]}]))
    code = main(["import", "--from", "label-studio", str(tmp_path / "e.json"), "--images", str(tmp_path / "imgs"),
                 "--out", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert code == 2
    assert "1 problem in" in err and "e.json: task 3: field 'data.image': image file 'x.png' not found" in err
    assert not (tmp_path / "ds").exists()


def test_bad_predictions_exit_2(tmp_path, capsys):
    (tmp_path / "p.jsonl").write_text('{"image": "a.png"}\n')
    assert main(["export-labels", "--to", "cvat", "--pred", str(tmp_path / "p.jsonl"), "--out",
                 str(tmp_path / "o.xml")]) == 2
    assert "p.jsonl:1: field 'frame_id': missing" in capsys.readouterr().err


def test_print_config(capsys):
    assert main(["import", "--print-config", "label-studio"]) == 0
    assert '<Relation value="front"/>' in capsys.readouterr().out


def test_the_labelling_package_never_imports_torch():
    code = ("import deepword.labelling, deepword.labelling.importer, deepword.labelling.export, sys; "
            "assert 'torch' not in sys.modules, 'torch imported'")
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)
