import numpy as np

from deepword.geometry import pairwise_iou
from deepword.relation_graph import relation_targets
from stages.relation.simulate import DetectionNoise, simulate_detections, with_simulated_detections
from tests.stages.relation import relation_data as rd

NOISY = DetectionNoise(copies=1, jitter=0.1, drop=0.3, false_positives=0.5)


def test_simulated_detections_keep_relations_consistent():
    rng = np.random.default_rng(0)
    for i in range(30):
        rec = rd.make_record(np.random.default_rng(i), i, n_cars=3, stray_wheel=True)
        sim = simulate_detections(rec, NOISY, rng, max_objects=16)
        original = set(rec.box_ids.tolist())
        kept = set(sim.box_ids.tolist()) & original
        false = set(sim.box_ids.tolist()) - original
        assert len(sim.boxes) <= 16 and len(set(sim.box_ids.tolist())) == len(sim.boxes)
        # a missed box takes its relations and couples with it; nothing is invented
        assert set(sim.relations) == {r for r in rec.relations if r[0] in kept and r[1] in kept}
        assert set(sim.wheel_pairs) == {p for p in rec.wheel_pairs if set(p) <= kept}
        # a false positive belongs to nothing, owns nothing, and matches no label of its class
        owner, couple, _ = relation_targets(sim)
        rows = np.isin(sim.box_ids, list(false))
        assert not owner[rows].any() and not couple[rows].any()
        for box in sim.boxes[rows]:
            same = rec.boxes[rec.class_ids == box[5], :4]
            assert pairwise_iou(box[None, :4], same).max() < 0.5
        # kept boxes moved but stay inside the image, with their class
        assert np.all(sim.xyxy >= 0) and np.all(sim.xyxy[:, [0, 2]] <= rec.width)
        assert np.all(sim.xyxy[:, 2] > sim.xyxy[:, 0]) and np.all(sim.xyxy[:, 3] > sim.xyxy[:, 1])


def test_simulation_is_seeded_and_appends_copies():
    recs = [rd.make_record(np.random.default_rng(i), i, n_cars=2) for i in range(5)]
    a = with_simulated_detections(recs, NOISY, seed=3)
    b = with_simulated_detections(recs, NOISY, seed=3)
    assert len(a) == 10 and a[:5] == recs
    assert all(np.array_equal(x.boxes, y.boxes) for x, y in zip(a, b, strict=True))
    assert with_simulated_detections(recs, DetectionNoise(copies=0), seed=3) == recs
    assert any(len(x.boxes) != len(r.boxes) or not np.allclose(x.boxes, r.boxes) for x, r in zip(a[5:], recs, strict=True))
