"""``deepword infer --rig``: a recorded drive's images, each one's camera and instant read from its path, the rig's
calibrations from a folder; each instant fused as ``--frame`` fuses one; clear errors where the names do not tell."""

import json
import shutil
from pathlib import Path

import pytest

from deepword.footprint import FootprintPrior
from deepword.inference.footprints import PRIOR_FILE, rig_view_of
from deepword.word_format import read_records
from stages.inference.infer import main as infer

REPO = Path(__file__).parents[3]
WOODSCAPE = {"front": "FV", "left": "MVL", "right": "MVR", "rear": "RV"}


@pytest.mark.parametrize("name, view", [
    ("drive/front/000042.png", ("front", 42)), ("drive/00042_MVL.png", ("left", 42)), ("rear/7.jpg", ("rear", 7)),
    ("x/00042_rv.png", ("rear", 42)), ("drive/000042.png", None), ("front/frame_a.png", None)])
def test_an_images_camera_and_instant_come_from_its_path(name, view, tmp_path):
    assert rig_view_of(tmp_path / name) == view


@pytest.fixture
def drive(generated_images, tmp_path):
    """Instant 7 in camera folders, instant 8 with WoodScape names; the calibrations in rig/ (WoodScape names)."""
    root, rig = tmp_path / "drive", tmp_path / "rig"
    rig.mkdir()
    for image in generated_images:
        camera = image.stem
        (root / camera).mkdir(parents=True)
        shutil.copy(image, root / camera / "000007.png")
        shutil.copy(image, root / f"00008_{WOODSCAPE[camera]}.png")
        cal = json.loads(image.with_suffix(".json").read_text())
        (rig / f"{WOODSCAPE[camera]}.json").write_text(json.dumps({k: v for k, v in cal.items() if k != "name"}))
    bev = tmp_path / "bev"
    bev.mkdir()
    prior = FootprintPrior(width=1.8, length=4.5, wheelbase=2.7, length_slope=1.0, length_offset=1.8,
                           track_inset=0.1, contact_shift=0.3, box_shift=2.5, height=1.5)
    (bev / PRIOR_FILE).write_text(json.dumps(prior.to_json()))
    return root, rig, bev


def test_a_drives_images_are_placed_by_their_paths_and_each_instant_gets_a_top_view(exported, generated_images, drive,
                                                                                   tmp_path):
    root, rig, bev = drive
    images = sorted(root.rglob("*.png"))
    out = tmp_path / "out"
    assert infer([*map(str, images), "--rig", str(rig), "--out", str(out), "--export", str(exported[0]),
                  "--bev", str(bev)]) == 0
    preds = read_records(out / "labels.jsonl", root=root)
    assert sorted((p.frame_id, p.camera) for p in preds) == sorted((f, c.stem) for f in (7, 8) for c in generated_images)
    assert sorted(p.name for p in (out / "top_views").iterdir()) == ["frame_000007.png", "frame_000008.png"]
    lines = [json.loads(line) for line in (out / "footprints.jsonl").read_text().splitlines()]
    assert [line["frame_id"] for line in lines] == [7, 8]


def test_an_instant_of_a_drive_gets_the_footprints_its_four_images_get_as_one_frame(generated_images, drive,
                                                                                    tmp_path):
    """On the generator's own boxes and relations (a smoke detector finds too little to place): --rig's instants
    give what --frame with the four calibration files gives."""
    from dataclasses import replace

    from omegaconf import OmegaConf

    from deepword.word_format import load_image
    from stages.data.synword import FrameGenerator
    from stages.inference.infer import parser, rig_records, write_predictions

    root, rig, bev = drive
    cfg = OmegaConf.to_container(OmegaConf.load(REPO / "conf/data/synword.yaml"), resolve=True)
    cfg["image_size"] = [320, 240]
    cfg["lens"]["randomise"] = False   # as the generated_images fixture renders them
    truth = {camera: rec for camera, _, rec in FrameGenerator(cfg, seed=0).render_frame(0)}
    images = sorted(root.rglob("*.png"))
    records = []
    for path in images:
        camera = next(c for c, w in WOODSCAPE.items() if path.parent.name == c or path.stem.endswith(w))
        rec = truth[camera]
        records.append(replace(rec, image=path.relative_to(root).as_posix(), extra={}))
    records = rig_records(images, records)
    out = tmp_path / "rig_out"
    args = parser().parse_args([*map(str, images), "--rig", str(rig), "--out", str(out), "--bev", str(bev)])
    out.mkdir()
    write_predictions(args, {}, records, lambda r: load_image(root, r), overlays=0)
    lines = [json.loads(line) for line in (out / "footprints.jsonl").read_text().splitlines()]

    one = tmp_path / "one_out"
    frame_images = [root / c.stem / "000007.png" for c in generated_images]
    args = parser().parse_args([*map(str, frame_images), "--frame", "--calibration",
                                *(str(p.with_suffix(".json")) for p in generated_images), "--out", str(one),
                                "--bev", str(bev)])
    one.mkdir()
    frame = [replace(truth[p.parent.name], image=p.relative_to(root).as_posix(), frame_id=0, extra={})
             for p in frame_images]
    write_predictions(args, {}, frame, lambda r: load_image(root, r), overlays=0)
    fused = json.loads((one / "footprints.jsonl").read_text())["footprints"]
    assert [line["frame_id"] for line in lines] == [7, 8]
    assert len(fused) >= 3 and lines[0]["footprints"] == lines[1]["footprints"] == fused


def test_a_drive_whose_names_or_calibrations_do_not_tell_is_a_clear_error(exported, drive, tmp_path, capsys):
    root, rig, bev = drive
    base = ["--rig", str(rig), "--out", str(tmp_path / "out"), "--export", str(exported[0]), "--bev", str(bev)]
    stray = root / "000009.png"
    shutil.copy(root / "front" / "000007.png", stray)
    assert infer([str(stray), *base]) == 2
    assert f"{stray}: --rig reads each image's camera and frame from its path" in capsys.readouterr().err
    again = root / "front" / "0007.png"
    shutil.copy(root / "front" / "000007.png", again)
    assert infer([str(root / "front" / "000007.png"), str(again), *base]) == 2
    assert "the front camera's image of frame 7 again" in capsys.readouterr().err
    (rig / "RV.json").unlink()
    assert infer([str(root / "rear" / "000007.png"), *base]) == 2
    assert f"{rig}: no calibration of the rear camera" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        infer([str(root / "rear" / "000007.png"), *base, "--frame"])
    assert "--rig goes with loose images" in capsys.readouterr().err
