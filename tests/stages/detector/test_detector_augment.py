import numpy as np
import pytest

from deepword.word_format import Record, load_image, parse_record
from stages.detector.augment import flip_image, flip_record, photometric_jitter


def record() -> Record:
    obj = {"image": "images/left/000001.png", "frame_id": 1, "camera": "left", "width": 100, "height": 50,
           "boxes": [[10, 5, 60, 40, 1.0, 0, 7], [12, 30, 22, 40, 1.0, 1, 3], [45, 31, 57, 41, 1.0, 1, 4],
                     [80, 20, 90, 30, 1.0, 1, 9]],
           "relations": [[7, 3, "rear"], [7, 4, "front"]], "wheel_pairs": [[3, 4]], "scene": "parking"}
    return parse_record(obj, "labels.jsonl", 1)


def test_flip_mirrors_boxes_and_keeps_relations_roles_couples():
    rec = record()
    flipped = flip_record(rec)
    assert np.allclose(flipped.xyxy[0], [40, 5, 90, 40])
    assert np.allclose(flipped.xyxy[:, 0], 100 - rec.xyxy[:, 2]) and np.allclose(flipped.xyxy[:, 2], 100 - rec.xyxy[:, 0])
    assert np.array_equal(flipped.xyxy[:, [1, 3]], rec.xyxy[:, [1, 3]])
    assert np.array_equal(flipped.boxes[:, 4:], rec.boxes[:, 4:])   # scores, classes, ids untouched
    # the rear wheel stays the rear one even though it is now on the right of the image
    assert flipped.relations == [(7, 3, "rear"), (7, 4, "front")] and flipped.wheel_pairs == [(3, 4)]
    assert flipped.owner_of() == rec.owner_of() and flipped.camera == rec.camera
    # still a valid WORD record, and flipping twice is the identity; the input is not modified
    parse_record(flipped.to_json(), "flipped", 1)
    assert np.allclose(flip_record(flipped).boxes, rec.boxes) and rec.xyxy[0, 0] == 10


def test_flipped_image_and_record_agree(tmp_path):
    import cv2

    rec = record()
    image = np.zeros((50, 100, 3), dtype=np.uint8)
    x1, y1, x2, y2 = rec.xyxy[0].astype(int)
    image[y1:y2, x1:x2] = 255
    (tmp_path / "images/left").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / rec.image), image)
    flipped_image, flipped = flip_image(load_image(tmp_path, rec)), flip_record(rec)
    fx1, fy1, fx2, fy2 = flipped.xyxy[0].astype(int)
    assert flipped_image[fy1:fy2, fx1:fx2].min() == 255
    assert flipped_image.sum() == image.sum()


def test_photometric_jitter_is_seeded_and_keeps_geometry():
    image = np.random.default_rng(0).integers(0, 255, size=(20, 30, 3), dtype=np.uint8)
    a = photometric_jitter(image, np.random.default_rng(1), 0.3, 0.3, 0.3)
    b = photometric_jitter(image, np.random.default_rng(1), 0.3, 0.3, 0.3)
    assert a.shape == image.shape and a.dtype == np.uint8 and np.array_equal(a, b)
    assert not np.array_equal(a, image)
    assert np.array_equal(photometric_jitter(image, np.random.default_rng(2), 0.0, 0.0, 0.0), image)


def test_photometric_jitter_hue_leaves_greys_and_is_off_at_zero():
    rng = np.random.default_rng(0)
    colour = rng.integers(40, 215, size=(20, 30, 3), dtype=np.uint8)
    grey = np.repeat(colour[..., :1], 3, axis=-1)
    assert np.array_equal(photometric_jitter(colour, np.random.default_rng(1), 0.0, 0.0, 0.0, 0.0), colour)
    turned = photometric_jitter(colour, np.random.default_rng(1), 0.0, 0.0, 0.0, 0.5)
    assert not np.array_equal(turned, colour)
    assert np.abs(photometric_jitter(grey, np.random.default_rng(1), 0.0, 0.0, 0.0, 0.5).astype(int) - grey).max() <= 1


def jitter_step_by_step(image, rng, brightness, contrast, saturation, hue):
    """The jitter's definition, one float pass per step in the drawn order (what the one composed map must equal)."""
    from deepword.colour import hue_rotation

    x = image.astype(np.float64)
    grey = x @ np.array([0.299, 0.587, 0.114])
    for i in rng.permutation(4 if hue > 0 else 3):
        if i == 0:
            x = x * rng.uniform(1 - brightness, 1 + brightness)
        elif i == 1:
            a = rng.uniform(1 - contrast, 1 + contrast)
            x = x * a + grey.mean() * (1 - a)
        elif i == 2:
            a = rng.uniform(1 - saturation, 1 + saturation)
            x = x * a + grey[..., None] * (1 - a)
        else:
            x = x @ hue_rotation(rng.uniform(-hue, hue)).T
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", range(6))
def test_photometric_jitter_in_one_pass_equals_its_steps_in_their_drawn_order(seed):
    image = np.random.default_rng(seed).integers(0, 256, size=(24, 40, 3), dtype=np.uint8)
    strengths = (0.4, 0.4, 0.4, 0.5)
    one_pass = photometric_jitter(image, np.random.default_rng(seed + 10), *strengths).astype(int)
    steps = jitter_step_by_step(image, np.random.default_rng(seed + 10), *strengths).astype(int)
    # one grey level at most, on the few pixels near a half level: OpenCV transforms 8-bit images in fixed point
    assert np.abs(one_pass - steps).max() <= 1
    assert (one_pass != steps).mean() < 0.1
    assert np.abs(one_pass - image).mean() > 5          # it did change the image


@pytest.mark.parametrize("factor", [0.37, 0.731, 0.993, 1.21])
def test_a_resized_region_is_the_resized_image_there_and_its_map_places_boxes_exactly(factor):
    """``resized_region`` gives the pixels the whole resize has in the region (up to its sub-pixel grid), and its
    map takes a square's box onto the square's pixels: white a pixel inside, black a pixel outside."""
    import cv2

    from stages.detector.augment import rescale, rescaled_size, resized_region

    rng = np.random.default_rng(int(factor * 1000))
    image = np.zeros((352, 480, 3), dtype=np.uint8)
    square = np.array([211.0, 97.0, 283.0, 161.0])
    image[97:161, 211:283] = 255
    image = cv2.GaussianBlur(image, (0, 0), 0.5)  # soft edges, as rendered objects have
    size = rescaled_size(480, 352, factor)
    whole, _ = rescale(image, np.zeros((0, 4)), factor)
    for _ in range(10):
        lo, hi = (square * factor)[:2] - 3, (square * factor)[2:] + 3  # regions about the square, cut anywhere
        x0, y0 = int(rng.integers(0, lo[0])), int(rng.integers(0, lo[1]))
        x1, y1 = int(rng.integers(hi[0], size[0] + 1)), int(rng.integers(hi[1], size[1] + 1))
        pixels, (sx, ox, sy, oy) = resized_region(image, size, x0, y0, x1, y1)
        assert pixels.shape == (y1 - y0, x1 - x0, 3)
        assert np.abs(pixels.astype(int) - whole[y0:y1, x0:x1].astype(int)).mean() < 2.0
        bx0, by0, bx1, by1 = square * [sx, sy, sx, sy] + [ox - x0, oy - y0, ox - x0, oy - y0]
        inside = pixels[int(np.ceil(by0)) + 1:int(by1) - 1, int(np.ceil(bx0)) + 1:int(bx1) - 1]
        assert inside.size and inside.min() >= 200
        ring = np.ones(pixels.shape[:2], dtype=bool)
        ring[max(0, int(by0) - 1):int(np.ceil(by1)) + 1, max(0, int(bx0) - 1):int(np.ceil(bx1)) + 1] = False
        assert pixels[ring].max() <= 55
