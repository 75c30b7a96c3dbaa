import math

import numpy as np

from deepword.word_format import Record
from stages.detector.misses import breakdown_metrics, recall_breakdown, write_breakdown


def record(boxes: list[tuple], width: int = 200, height: int = 100) -> Record:
    """A record of (x1, y1, x2, y2, score, class) boxes, box ids 0.."""
    arr = np.array([(*b, i) for i, b in enumerate(boxes)], dtype=np.float64).reshape(-1, 7)
    return Record(image="a.png", frame_id="f0", camera="front", width=width, height=height, boxes=arr, relations=[], wheel_pairs=[])


def rows_by_group(rows: list[dict]) -> dict[tuple[str, str], dict]:
    return {(r["class"], r["group"]): r for r in rows}


def test_recall_by_size_occlusion_and_border():
    truth = record([(10, 10, 90, 60, 1, 0),      # large vehicle (shorter side 50), found
                    (60, 20, 100, 50, 1, 0),     # vehicle 40 x 30, 75 % inside the first: occluded, missed
                    (0, 40, 30, 90, 1, 0),       # vehicle at the left border, found only at score 0.2
                    (20, 50, 30, 60, 1, 1),      # 10 px wheel, found
                    (150, 80, 156, 86, 1, 1)])   # 6 px wheel, missed
    prediction = record([(11, 10, 90, 61, 0.9, 0), (0, 41, 30, 90, 0.2, 0), (20, 50, 30, 61, 0.8, 1),
                         (150, 0, 160, 10, 0.9, 1)])   # a false wheel elsewhere finds nothing
    rows = rows_by_group(recall_breakdown([truth], [prediction], ["vehicle", "wheel"], min_score=0.3))
    assert rows[("vehicle", "all")]["boxes"] == 3 and rows[("vehicle", "all")]["found"] == 1
    assert rows[("vehicle", "size 32-64 px")]["recall"] == 100.0    # the 50 px one
    assert rows[("vehicle", "size 16-32 px")]["boxes"] == 2 and rows[("vehicle", "size 16-32 px")]["recall"] == 0.0
    assert rows[("vehicle", "occluded")]["boxes"] == 1 and rows[("vehicle", "occluded")]["found"] == 0
    assert rows[("vehicle", "at the border")]["boxes"] == 1 and rows[("vehicle", "at the border")]["found"] == 0
    assert rows[("wheel", "size 8-16 px")]["recall"] == 100.0 and rows[("wheel", "size <8 px")]["recall"] == 0.0
    assert math.isnan(rows[("wheel", "size >=64 px")]["recall"])
    assert ("wheel", "occluded") not in rows   # inside its vehicle's box is where a wheel belongs
    # a lower score threshold finds the border vehicle
    low = rows_by_group(recall_breakdown([truth], [prediction], ["vehicle", "wheel"], min_score=0.1))
    assert low[("vehicle", "at the border")]["found"] == 1


def test_breakdown_metrics_and_table(tmp_path):
    truth = record([(10, 10, 90, 60, 1, 0), (20, 50, 30, 60, 1, 1)])
    rows = recall_breakdown([truth], [record([(10, 10, 90, 60, 0.9, 0)])], ["vehicle", "wheel"], 0.3)
    metrics = breakdown_metrics(rows, "test")
    assert metrics["detector.test.recall.vehicle.size_32-64"] == 100.0
    assert metrics["detector.test.recall.wheel.size_8-16"] == 0.0
    assert "detector.test.recall.wheel.size_ge64" not in metrics   # empty groups are left out
    write_breakdown(tmp_path / "misses.md", rows, 0.3, "test")
    text = (tmp_path / "misses.md").read_text()
    assert "| size 32-64 px | 1 | 100.0 % | 0 | – |" in text
