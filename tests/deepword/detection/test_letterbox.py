import numpy as np
import pytest

from deepword.detection.letterbox import (
    MEAN,
    boxes_to_input,
    boxes_to_original,
    letterbox_for,
    letterbox_image,
    preprocess,
)


def test_letterbox_of_the_fisheye_size():
    box = letterbox_for(640, 480, 320, 256)
    assert box.scale == 0.5 and (box.pad_x, box.pad_y) == (0, 8)
    assert letterbox_for(640, 480, 384, 288).scale == pytest.approx(0.6)


def test_boxes_round_trip_and_clip():
    box = letterbox_for(640, 480, 320, 256)
    xyxy = np.array([[10.0, 20.0, 110.0, 220.0], [600.0, 400.0, 640.0, 480.0]])
    inp = boxes_to_input(xyxy, box)
    assert np.allclose(inp[0], [5, 18, 55, 118])
    assert np.allclose(boxes_to_original(inp, box, 640, 480), xyxy)
    outside = boxes_to_original(np.array([[-10.0, 0.0, 330.0, 260.0]]), box, 640, 480)
    assert np.allclose(outside, [[0, 0, 640, 480]])


def test_letterboxed_image_places_content_and_pads_with_mean():
    image = np.full((480, 640, 3), 200, dtype=np.uint8)
    out = letterbox_image(image, letterbox_for(640, 480, 320, 256))
    assert out.shape == (256, 320, 3)
    assert (out[8:248] == 200).all() and (out[:8] == np.round(MEAN * 255)).all() and (out[248:] == out[0, 0]).all()
    x, box = preprocess(image, 320, 256)
    assert x.shape == (3, 256, 320) and x.dtype == np.float32 and box.pad_y == 8
    assert np.allclose(x[:, 0, 0], 0, atol=0.01)  # the padding is ~0 after normalisation
