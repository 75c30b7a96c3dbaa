"""``deepword tune``: the operating point chosen again on labelled images, written as a bundle infer uses."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from deepword.inference.runtime import BUNDLE_FILE, OnnxDetector
from stages.inference.tune import main as tune

REPO = Path(__file__).resolve().parents[3]


def test_on_the_export_stages_val_split_tune_chooses_the_export_stages_point(upstream, exported, tmp_path):
    """The same images, grid, protocol and method as the export stage (the bundle records them): the same point and
    the same val pair_f1, though tune runs the ONNX model on each subset where the stage embedded each box once."""
    out_dir, metrics = exported
    assert tune(["--dataset", str(upstream["data"]), "--split", "val", "--export", str(out_dir),
                 "--out", str(tmp_path / "tuned")]) == 0
    shipped = json.loads((out_dir / BUNDLE_FILE).read_text())["detector"]
    tuned = json.loads((tmp_path / "tuned" / BUNDLE_FILE).read_text())
    assert tuned["detector"]["operating_point"] == shipped["operating_point"]
    assert tuned["detector"]["min_side"] == {"vehicle": 0.0, **shipped["min_side"]}
    entry = tuned["tuned"]
    assert entry["method"] == "deepword_then_logic" and entry["images"] == 1 and entry["points"] == 18
    assert entry["smoothing"] == shipped["operating_point_search"]["smoothing"] == 0
    assert entry["pair_f1"] == pytest.approx(metrics["export.detector.val_pair_f1"], abs=1e-9)
    assert entry["pair_f1_at_bundle_point"] == pytest.approx(entry["pair_f1"], abs=1e-9)
    assert (tmp_path / "tuned" / "artifacts" / "operating_point.png").is_file()
    assert "| **chosen** |" in (tmp_path / "tuned" / "artifacts" / "operating_point.md").read_text()


def test_the_tuned_bundle_is_what_infer_keeps_detections_at(upstream, exported, tmp_path, capsys):
    out = tmp_path / "tuned"
    args = ["--dataset", str(upstream["data"]), "--split", "test", "--export", str(exported[0]), "--out", str(out),
            "--grid", "0.3", "--min-side", "wheel=5"]
    assert tune(args) == 0
    detector = OnnxDetector(out)
    assert detector.class_thresholds == (0.3, 0.3) and detector.class_min_sides == (0.0, 5.0)
    printed = capsys.readouterr()
    assert "minimum sides {'vehicle': 0.0, 'wheel': 5.0}" in printed.out
    # stderr is no terminal here: progress is whole lines (deepword/progress.py), not a bar redrawn with \r
    assert "\r" not in printed.err and "detector: " in printed.err
    assert any(line.startswith("relation model on subsets of the boxes: ") for line in printed.err.splitlines())
    assert tune(args[:-1] + ["wheel=6"]) == 0   # a bundle tune wrote may be replaced
    assert OnnxDetector(out).class_min_sides == (0.0, 6.0)


@pytest.mark.parametrize("extra, message", [
    (["--split", "val", "--min-side", "bus=3"], "--min-side: expected CLASS=PX"),
    (["--split", "val", "--grid", "0.2,x"], "--grid: '0.2,x' is not a comma-separated list"),
    (["--split", "nope"], "unknown split 'nope'"),
    (["--split", "val", "--smoothing", "-1"], "--smoothing -1: expected a number of grid steps >= 0"),
])
def test_bad_options_are_one_line_errors(upstream, exported, tmp_path, capsys, extra, message):
    assert tune(["--dataset", str(upstream["data"]), "--export", str(exported[0]), "--out", str(tmp_path / "t"),
                 *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "t").exists()


def test_split_needs_a_data_stage_output_and_out_must_not_be_the_bundle(upstream, exported, tmp_path, capsys):
    plain = tmp_path / "plain"
    shutil.copytree(upstream["data"], plain)
    (plain / "splits.json").unlink()
    (plain / "dataset.json").unlink()
    assert tune(["--dataset", str(plain), "--split", "val", "--export", str(exported[0]), "--out",
                 str(tmp_path / "t")]) == 2
    assert "has no splits.json" in capsys.readouterr().err
    assert tune(["--dataset", str(plain), "--export", str(exported[0]), "--out", str(exported[0]),
                 "--grid", "0.5"]) == 2
    assert "--out must be a new folder" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    assert tune(["--dataset", str(plain), "--export", str(exported[0]), "--out", str(tmp_path / "other"),
                 "--grid", "0.5"]) == 2
    assert "exists and is not a bundle" in capsys.readouterr().err


def test_tune_never_imports_torch(upstream, exported, tmp_path):
    code = ("import sys; from stages.cli import main; "
            f"rc = main(['tune', '--dataset', {str(upstream['data'])!r}, '--split', 'test', '--export', "
            f"{str(exported[0])!r}, '--out', {str(tmp_path / 't')!r}, '--grid', '0.5']); "
            "assert rc == 0, rc; loaded = [m for m in ('torch', 'lightning') if m in sys.modules]; "
            "assert not loaded, loaded")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_a_prior_steadies_the_choice_and_is_recorded(upstream, exported, tmp_path, capsys):
    """--prior adds another set's counts weighed as --prior-images: weighed as nothing the choice is tune's own (and
    the prior's images, which share paths with the tuning images, are kept apart), weighed as a million it is what
    tune chooses on the prior alone."""
    base = ["--dataset", str(upstream["data"]), "--split", "val", "--export", str(exported[0])]
    prior = ["--prior", str(upstream["data"]), "--prior-split", "test"]
    assert tune([*base, "--out", str(tmp_path / "own")]) == 0
    assert tune([*base, *prior, "--prior-images", "0", "--out", str(tmp_path / "zero")]) == 0
    assert tune(["--dataset", str(upstream["data"]), "--split", "test", "--export", str(exported[0]),
                 "--out", str(tmp_path / "on_test")]) == 0
    assert tune([*base, *prior, "--prior-images", "1e6", "--out", str(tmp_path / "heavy")]) == 0
    read = {name: json.loads((tmp_path / name / BUNDLE_FILE).read_text()) for name in ("own", "zero", "on_test", "heavy")}
    assert read["zero"]["detector"]["operating_point"] == read["own"]["detector"]["operating_point"]
    assert read["zero"]["tuned"]["pair_f1"] == pytest.approx(read["own"]["tuned"]["pair_f1"])
    heavy = read["heavy"]["tuned"]
    assert heavy["prior"]["images"] == 7 and heavy["prior"]["weighed_as_images"] == 1e6 and heavy["images"] == 1
    assert heavy["prior"]["pair_f1_with_prior"] == pytest.approx(read["on_test"]["tuned"]["pair_f1"], abs=1e-3)
    capsys.readouterr()
    assert tune([*base, *prior, "--prior-images", "-1", "--out", str(tmp_path / "bad")]) == 2
    assert "--prior-images -1: expected a weight >= 0" in capsys.readouterr().err
