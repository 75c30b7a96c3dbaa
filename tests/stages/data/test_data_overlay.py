"""Fig. 5-style overlays, contact sheets and the show CLI."""

import cv2
import numpy as np

from deepword.overlay import COUPLE_RGB, FRONT_RGB, REAR_RGB, contact_sheet, draw_relations
from deepword.word_format import Record
from stages.data.show import main as show_main


def _record():
    boxes = np.array([[20, 20, 180, 100, 1, 0, 0], [30, 70, 50, 95, 1, 1, 1], [140, 70, 160, 95, 1, 1, 2]], float)
    return Record(image="images/front/000000.png", frame_id=0, camera="front", width=200, height=120, boxes=boxes,
                  relations=[(0, 1, "rear"), (0, 2, "front")], wheel_pairs=[(1, 2)])


def _has_colour(img, x, rows, rgb) -> bool:
    """Some pixel of column ``x`` in ``rows`` has the hue of ``rgb`` (lines are anti-aliased on black)."""
    ref = np.array(rgb, float) / max(rgb)
    for y in rows:
        p = img[y, x].astype(float)
        if p.max() > 100 and np.allclose(p / p.max(), ref, atol=0.08):
            return True
    return False


def test_draw_relations_colours():
    out = draw_relations(np.zeros((120, 200, 3), np.uint8), _record())
    assert _has_colour(out, 95, range(78, 88), COUPLE_RGB)  # between the wheel centres (y = 82)
    # rear wheel (40, 82) -> vehicle centre (100, 60) is green; front wheel (150, 82) -> centre is blue
    assert _has_colour(out, 60, range(65, 85), REAR_RGB) and not _has_colour(out, 60, range(65, 85), FRONT_RGB)
    assert _has_colour(out, 130, range(65, 80), FRONT_RGB) and not _has_colour(out, 130, range(65, 80), REAR_RGB)
    assert out[20, 100].any()  # the vehicle box's top edge


def test_contact_sheet_tiles_and_resizes():
    imgs = [np.full((10, 20, 3), i * 40, np.uint8) for i in range(5)] + [np.zeros((5, 5, 3), np.uint8)]
    sheet = contact_sheet(imgs, 4)
    assert sheet.shape == (2 * 14 + 4, 4 * 24 + 4, 3)
    assert (sheet[4:14, 28:48] == 40).all()


def test_show_cli_writes_a_sheet(synword_sample, tmp_path):
    root, records = synword_sample
    from deepword.word_format import write_records

    write_records(root / "labels.jsonl", records)
    out = tmp_path / "sheet.png"
    show_main([str(root), "--n", "2", "--out", str(out)])
    sheet = cv2.imread(str(out))
    assert sheet is not None and sheet.shape[1] > 4 * 320
