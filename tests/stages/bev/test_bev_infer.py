"""One code path for a frame's footprints: the bev stage run on rendered SynWORD frames and ``deepword infer`` on the
same frames' predictions give the same fused footprints (the bev stage's prior, heading table included, and fusion
radius), infer writes the frames' top views beside the overlays; with the held-out domain among its inputs the bev
stage scores it too, under ``bev.shift.*``."""

import json
import math
from pathlib import Path

import cv2
import pytest
from omegaconf import OmegaConf

from deepword.format_3d import record_objects_3d
from deepword.wheel_roles import FOOTPRINT, ROLES_FROM_KEY
from deepword.word_format import load_image, read_records, write_dataset_index, write_records
from stages.bev.stage import run
from stages.data.synword import generate
from stages.inference.infer import parser, write_predictions
from tests.stage_inputs import stage_inputs

CONF = Path(__file__).resolve().parents[3] / "conf"
METHOD = "deepword"


def _dataset(root: Path, frames: int, seed: int, test_from: int) -> list:
    """A data-stage-like directory of rendered frames; frames ``test_from`` on are the test split."""
    cfg = {**OmegaConf.to_container(OmegaConf.load(CONF / "data" / "synword.yaml"), resolve=True),
           "frames": frames, "workers": 1}
    records = generate(cfg, seed=seed, out_dir=root, workers=1, progress=False)
    write_records(root / "labels.jsonl", records)
    records = read_records(root / "labels.jsonl")
    test = [r.image for r in records if r.frame_id >= test_from]
    write_dataset_index(root, root, {"train": [r.image for r in records if r.frame_id < test_from], "val": [],
                                     "test": test, "hard": test[::2]})
    return [r for r in records if r.frame_id >= test_from]


def _predictions(path: Path, records: list) -> None:
    """The test records as a relation method's predictions (their own relations and roles, the role head's way)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_records(path, records)


@pytest.fixture(scope="module")
def bev_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("bev_infer")
    test = _dataset(base / "data", frames=5, seed=3, test_from=3)
    heldout = _dataset(base / "shift_data", frames=2, seed=11, test_from=0)
    _predictions(base / "evaluate" / "predictions" / f"gt_{METHOD}.jsonl", test)
    _predictions(base / "evaluate" / "shift" / "predictions" / f"gt_{METHOD}.jsonl", heldout)
    bcfg = {**OmegaConf.to_container(OmegaConf.load(CONF / "bev" / "default.yaml")), "methods": [METHOD],
            "box_sources": ["gt"], "figures": 1}
    out = base / "bev"
    out.mkdir()
    dirs = {name: base / name for name in ("data", "evaluate", "shift_data")}
    metrics = run(OmegaConf.create({"bev": bcfg, "seed": 0}), stage_inputs("bev", dirs), out)
    return base, test, heldout, out, metrics


def test_infer_gives_the_bev_stages_frame_footprints_and_draws_the_frames_top_view(bev_run):
    base, test, _, bev, _ = bev_run
    prior = json.loads((bev / "footprint_prior.json").read_text())
    assert prior["heading"], "the prior infer reads holds the heading table fitted on train"
    out = base / "infer"
    args = parser().parse_args(["--dataset", str(base / "data"), "--out", str(out), "--bev", str(bev)])
    out.mkdir()
    preds = write_predictions(args, {}, test, lambda r: load_image(base / "data", r), overlays=len(test))

    by_stage = (bev / "footprints" / f"gt_{METHOD}.jsonl").read_text().splitlines()
    by_infer = (out / "footprints.jsonl").read_text().splitlines()
    assert len(by_infer) == len({r.frame_id for r in test}) == 2
    assert by_infer == by_stage   # the same footprints, evidence, cameras, confidences and headings' sources
    assert any(f["heading_from"] == "roles" for line in by_infer for f in json.loads(line)["footprints"])
    assert any(len(f["seen_by"]) > 1 for line in by_infer for f in json.loads(line)["footprints"])

    # each prediction carries its vehicles' fused footprints: the frame's rows, keyed by the image's box ids
    rows = {(f["center"][0], f["center"][1], f["yaw"]) for line in by_infer for f in json.loads(line)["footprints"]}
    for pred in preds:
        vehicles = [v for v in pred.extra["objects_3d"].values() if "center" in v]
        assert vehicles and all((v["center"][0], v["center"][1], v["yaw"]) in rows for v in vehicles)
        assert pred.camera in {c for v in vehicles for c in v["seen_by"]}

    # the frames' top views beside the overlays; each overlay with its image's top view to its right
    views = sorted(p.name for p in (out / "top_views").iterdir())
    assert views == [f"frame_{f:06d}.png" for f in sorted({r.frame_id for r in test})]
    overlay = cv2.imread(str(out / "overlays" / (Path(test[0].image).with_suffix("").as_posix().replace("/", "__")
                                                  + ".png")))
    assert overlay.shape[0] == test[0].height and overlay.shape[1] > test[0].width + 100


def test_the_bev_stage_scores_the_held_out_domain_beside_in_domain(bev_run):
    base, test, heldout, bev, metrics = bev_run
    for root in ("bev", "bev.shift"):
        assert 0 <= metrics[f"{root}.gt.{METHOD}.all.ap"] <= 100
        assert f"{root}.gt.{METHOD}.center_err_m" in metrics and f"{root}.gt.box_bottom.all.ap" in metrics

    def within_range(records) -> int:
        seen = {(r.frame_id, round(b.x, 2), round(b.y, 2)) for r in records
                for b in record_objects_3d(r, "test")[0].values() if math.hypot(b.x, b.y) <= 10}
        return len(seen)

    assert metrics[f"bev.gt.{METHOD}.all.vehicles"] == within_range(test)
    assert metrics[f"bev.shift.gt.{METHOD}.all.vehicles"] == within_range(heldout)
    lines = (bev / "shift" / "footprints" / f"gt_{METHOD}.jsonl").read_text().splitlines()
    assert [json.loads(line)["frame_id"] for line in lines] == sorted({r.frame_id for r in heldout})
    report = (bev / "bev_report.md").read_text()
    assert "# Held-out domain" in report and "held-out gt boxes: detection scores" in report
    assert json.loads((bev / "bev.json").read_text())["shift"]["frames"] == 2
    assert sorted(p.name for p in (bev / "artifacts").glob("shift_top_view_*.png"))


def test_infer_names_each_wheels_role_from_its_vehicles_footprint_and_the_bev_stage_scores_it(bev_run):
    """The predictions carry the true roles (a role head that is always right), so the footprints face the right way
    and the roles read back from them must be the true ones; ``--roles network`` writes the method's roles as they
    were."""
    base, test, _, bev, metrics = bev_run
    truth = {(r.image, v, w): role for r in test for v, w, role in r.relations}
    for roles, out in (("front", base / "infer_roles"), ("network", base / "infer_network_roles")):
        args = parser().parse_args(["--dataset", str(base / "data"), "--out", str(out), "--bev", str(bev),
                                    "--roles", roles])
        out.mkdir()
        preds = write_predictions(args, {}, test, lambda r: load_image(base / "data", r), overlays=0)
        assert len(read_records(out / "labels.jsonl")) == len(preds)   # what infer writes passes the reader's checks
        written = {(p.image, v, w): role for p in preds for v, w, role in p.relations}
        if roles == "network":
            assert written == truth and not any(ROLES_FROM_KEY in p.extra for p in preds)
            continue
        decided = sum(p.extra[ROLES_FROM_KEY][FOOTPRINT] for p in preds)
        assert decided >= 0.8 * len(truth), "most wheels have a contact and a footprint of their vehicle"
        known = [k for k in truth if truth[k]]
        right = sum(written[k] == truth[k] for k in known)
        assert right >= 0.9 * len(known)
        # the bev stage scores the roles infer writes
        assert metrics["bev.gt.roles.acc"] == pytest.approx(100.0 * right / len(known))
        assert metrics["bev.gt.roles.relations"] == len(known)
        role_of = {(p.image, w): role for p in preds for _, w, role in p.relations}
        for p in preds:   # couples rear first where their roles differ
            for a, b in p.wheel_pairs:
                assert (role_of.get((p.image, a)), role_of.get((p.image, b))) != ("front", "rear")
    for root in ("bev", "bev.shift"):
        assert metrics[f"{root}.gt.roles.relations"] > 0
        assert metrics[f"{root}.gt.roles.network_acc"] == 100.0   # the predictions' roles are the truth's
        assert metrics[f"{root}.gt.roles.acc"] > 50.0   # (a footprint the heading prior turns takes its roles along)
    assert "front / rear roles are right for" in (bev / "bev_report.md").read_text()


def test_footprints_fitted_in_worker_processes_are_the_ones_fitted_in_one(bev_run, monkeypatch):
    """``deepword infer --threads N`` fits a dataset's frames in N processes; a frame's footprints depend on that frame
    alone, so they are the same."""
    from deepword import frame_processes
    from deepword.format_3d import record_camera
    from deepword.inference import footprints

    base, test, _, bev, _ = bev_run
    prior = footprints.load_prior(bev)
    views = [(r, record_camera(r, "the test")) for r in test]
    monkeypatch.setattr(frame_processes, "FRAMES_PER_TASK", 1)   # the fixture's two test frames: one a process
    seen = []
    one = footprints.estimate_frames(views, prior, workers=1)
    two = footprints.estimate_frames(views, prior, workers=2,
                                     progress=lambda items, n: (seen.append(n), items)[1])
    assert seen == [2] and list(one) == list(two) == sorted({r.frame_id for r in test})
    assert all(one[f].fused == two[f].fused and one[f].fused for f in one)


def test_detected_boxes_footprints_come_from_the_footprint_points_predictions_in_the_stage_and_in_infer(tmp_path):
    """Evaluate's predictions on the footprint point's detections (here the whole records) are what the bev stage
    places detected boxes from, where the relations it scored (here without each image's first vehicle) see fewer;
    ``deepword infer`` places the same from them, and writes the scored predictions, each naming only its own
    boxes."""
    from dataclasses import replace

    import numpy as np

    test = _dataset(tmp_path / "data", frames=4, seed=3, test_from=2)

    def without_first_vehicle(rec):
        first = int(rec.box_ids[rec.class_ids == 0][0])
        keep = rec.box_ids != first
        objects = {k: v for k, v in rec.extra["objects_3d"].items() if int(k) != first}
        return replace(rec, boxes=rec.boxes[keep].copy(), relations=[r for r in rec.relations if r[0] != first],
                       extra={**rec.extra, "objects_3d": objects})

    scored = [without_first_vehicle(r) for r in test]
    predictions = tmp_path / "evaluate" / "predictions"
    _predictions(predictions / f"gt_{METHOD}.jsonl", test)
    _predictions(predictions / f"detected_{METHOD}.jsonl", scored)
    _predictions(predictions / f"footprints_{METHOD}.jsonl", test)
    bcfg = {**OmegaConf.to_container(OmegaConf.load(CONF / "bev" / "default.yaml")), "methods": [METHOD],
            "box_sources": ["gt", "detected"], "figures": 0}
    out = tmp_path / "bev"
    out.mkdir()
    dirs = {name: tmp_path / name for name in ("data", "evaluate")}
    run(OmegaConf.create({"bev": bcfg, "seed": 0}), stage_inputs("bev", dirs), out)
    by_stage = (out / "footprints" / f"detected_{METHOD}.jsonl").read_text()
    assert by_stage == (out / "footprints" / f"gt_{METHOD}.jsonl").read_text()

    infer_out = tmp_path / "infer"
    infer_out.mkdir()
    args = parser().parse_args(["--dataset", str(tmp_path / "data"), "--out", str(infer_out), "--bev", str(out)])
    preds = write_predictions(args, {}, scored, lambda r: load_image(tmp_path / "data", r), overlays=0,
                              placed=test)
    assert (infer_out / "footprints.jsonl").read_text() == by_stage
    for pred, rec in zip(preds, scored, strict=True):
        assert np.array_equal(pred.boxes, rec.boxes)
        assert {int(k) for k in pred.extra["objects_3d"]} <= set(rec.box_ids.tolist())

    # without them, the detected boxes are placed from the scored predictions: fewer vehicles
    (predictions / f"footprints_{METHOD}.jsonl").unlink()
    again = tmp_path / "bev_again"
    again.mkdir()
    run(OmegaConf.create({"bev": bcfg, "seed": 0}), stage_inputs("bev", dirs), again)
    assert (again / "footprints" / f"detected_{METHOD}.jsonl").read_text() != by_stage
