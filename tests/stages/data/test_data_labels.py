"""Labels made from the render: consistency, the paper's hard cases, splits by frame."""

import numpy as np

from deepword.geometry import containment
from deepword.word_format import VEHICLE, WHEEL, Record, read_records, write_records
from stages.data.stats import boxes_meet_at_wheel, make_splits, multi_box_wheels, split_metrics
from stages.data.synword import FrameGenerator
from tests.stages.data.data_helpers import synword_cfg


def test_records_are_valid_word_records_with_images(synword_sample):
    out, records = synword_sample
    assert records
    write_records(out / "labels.jsonl", records)
    again = read_records(out / "labels.jsonl", check_images=True)  # the one validator accepts them all
    assert [r.image for r in again] == [r.image for r in records]


def test_labels_are_consistent(synword_sample):
    _, records = synword_sample
    for rec in records:
        cls = dict(zip(rec.box_ids.tolist(), rec.class_ids.tolist(), strict=True))
        box = {int(b[6]): b[:4] for b in rec.boxes}
        assert rec.relations, "kept images have at least one owner-member relation"
        owners = {}
        for v, w, role in rec.relations:
            assert cls[v] == VEHICLE and cls[w] == WHEEL and role in ("front", "rear")
            assert w not in owners
            owners[w] = v
            # the vehicle's box includes its visible wheels
            assert containment(box[w][None], box[v][None])[0, 0] == 1.0
        xyxy = rec.xyxy
        assert (xyxy[:, 0] >= 0).all() and (xyxy[:, 1] >= 0).all()
        assert (xyxy[:, 2] <= rec.width).all() and (xyxy[:, 3] <= rec.height).all()
        assert (xyxy[:, 2] > xyxy[:, 0]).all() and (xyxy[:, 3] > xyxy[:, 1]).all()
        roles = {w: r for _, w, r in rec.relations}
        for rear, front in rec.wheel_pairs:
            assert owners.get(rear) == owners.get(front)
            if rear in roles:
                assert roles[rear] == "rear" and roles[front] == "front"


def test_a_frames_four_cameras_share_the_frame_id(synword_sample):
    _, records = synword_sample
    frames = {}
    for r in records:
        frames.setdefault(r.frame_id, set()).add(r.camera)
        assert r.image == f"images/{r.camera}/{r.frame_id:06d}.png"
    assert any(len(c) == 4 for c in frames.values())


def test_the_papers_hard_cases_occur(synword_sample):
    _, records = synword_sample
    assert sum(multi_box_wheels(r) for r in records) >= 3   # Fig. 2: a wheel wholly inside two vehicle boxes
    assert sum(boxes_meet_at_wheel(r) for r in records) >= 3  # Fig. 7: two boxes intersecting at a wheel
    assert any(r.n_vehicles > 3 for r in records) and any(r.n_vehicles <= 3 for r in records)


def test_occluded_and_tiny_objects_are_not_annotated():
    cfg = synword_cfg(frames=1)
    gen = FrameGenerator(cfg, seed=7)
    rng = gen.frame_rng(3)
    scene = gen.sampler.sample(rng)
    from stages.data.render import ObjectStats

    nv = len(scene.vehicles)
    vstats = [ObjectStats(100, 100, (10, 10, 60, 40))] + [ObjectStats(100, 10, (0, 0, 30, 30), (0, 0, 50, 35))] * (nv - 1)
    wstats = [ObjectStats(50, 50, (20, 30, 30, 40)), ObjectStats(50, 50, (40, 30, 43, 40))]
    wstats += [ObjectStats(0, 0, None)] * (4 * nv - 2)
    rec = gen.labels(3, gen.tables(3)[0].cam, scene, vstats, wstats, rng)
    # vehicle 0 fully visible; the others 10 % visible (< min_visible_fraction); wheel 1 is 3 px wide
    assert rec.n_vehicles == 1 and rec.n_wheels == 1
    v, w, role = rec.relations[0]
    assert role == "rear"
    # what is visible but not annotated becomes an ignore region where it would be seen unoccluded (its visible
    # box where that is not known); nothing invisible does
    assert rec.ignore.tolist() == [[0, 0, 50, 35, VEHICLE]] * (nv - 1) + [[40, 30, 43, 40, WHEEL]]
    again = Record(**{**rec.__dict__, "ignore": rec.ignore[:0]})
    assert again.to_json() | {"ignore": rec.to_json()["ignore"]} == rec.to_json()  # the labels are the same


def test_ignore_regions_are_the_unannotated_visible_objects(synword_sample):
    _, records = synword_sample
    assert sum(len(r.ignore) for r in records) > 0  # occlusion and distance hide something in every sample
    for rec in records:
        for x1, y1, x2, y2, cls in rec.ignore:
            assert cls in (VEHICLE, WHEEL) and 0 <= x1 < x2 <= rec.width and 0 <= y1 < y2 <= rec.height


def test_an_objects_unoccluded_box_holds_its_visible_box():
    cfg = synword_cfg(frames=1)
    gen = FrameGenerator(cfg, seed=3)
    rng = gen.frame_rng(0)
    scene = gen.sampler.sample(rng)
    from stages.data.backdrop import draw_look, ground_texture
    from stages.data.render import render_camera

    look = draw_look(rng, gen.domain.draw(rng, "skies"), gen.domain.draw(rng, "grounds"), gen.domain.sun_elevation_deg)
    tex = ground_texture(gen.grounds, look, scene)
    seen = 0
    for tables in gen.tables(0):
        _, _, vstats, wstats = render_camera(tables, scene, tex, look, gen.clouds)
        for st in vstats + wstats:
            if st.bbox is None:
                continue
            seen += 1
            (a, b, c, d), (e, f, g, h) = st.bbox, st.own_bbox
            assert e <= a and f <= b and g >= c and h >= d and st.visible_px <= st.own_px
    assert seen


def test_split_by_frame_and_difficulty_subsets(synword_sample):
    _, records = synword_sample
    splits = make_splits(records, {"train": 0.6, "val": 0.2, "test": 0.2}, seed=1, max_easy_vehicles=3)
    by_image = {r.image: r for r in records}
    frames = {s: {by_image[i].frame_id for i in splits[s]} for s in ("train", "val", "test")}
    assert not (frames["train"] & frames["val"]) and not (frames["train"] & frames["test"])
    assert not (frames["val"] & frames["test"])
    assert sum(len(splits[s]) for s in ("train", "val", "test")) == len(records)
    assert set(splits["easy"]) | set(splits["hard"]) == set(splits["test"])
    assert all(by_image[i].n_vehicles > 3 for i in splits["hard"])
    metrics = split_metrics(records, splits)
    assert metrics["data.test.easy_images"] + metrics["data.test.hard_images"] == metrics["data.test.images"]
    assert 0 <= metrics["data.train.multi_box_wheel_share"] <= 100


def _record(boxes, relations):
    arr = np.array([[*b, 1.0, c, i] for i, (b, c) in enumerate(boxes)], float)
    return Record(image="x.png", frame_id=0, camera="front", width=100, height=100, boxes=arr,
                  relations=relations, wheel_pairs=[])


def test_multi_box_wheel_counts_a_wheel_inside_two_vehicle_boxes():
    # Fig. 2: the near vehicle (0, big) owns wheel 2, which also lies inside the far, smaller vehicle 1's box
    rec = _record([((0, 0, 90, 90), VEHICLE), ((40, 40, 80, 80), VEHICLE), ((50, 60, 60, 70), WHEEL)], [(0, 2, "rear")])
    assert multi_box_wheels(rec) == 1


def test_each_calibration_outlines_where_the_egos_body_covers_its_image(synword_sample):
    """The renderer's ego body, as a rig's calibration would give it (``calibration.ego_body``): drawn back from the
    outline, it covers the pixels the renderer put the ego's body in, to within the outline's simplification."""
    from deepword.format_3d import record_camera

    _, records = synword_sample
    generator = FrameGenerator(synword_cfg(frames=12), seed=7)
    covered = 0
    for rec in records[:8]:
        rendered = next(t.ego_mask for t in generator.tables(rec.frame_id) if t.cam.name == rec.camera).astype(bool)
        drawn = record_camera(rec, "test").ego_mask
        assert drawn is not None and drawn.shape == rendered.shape, rec.image
        assert (drawn != rendered).sum() <= 0.05 * max(rendered.sum(), 1), rec.image
        covered += int(rendered.any())
    assert covered >= 4   # the body is in most cameras' view
