"""Checking every image of a real dataset up front: header checks vs decoding.

``read_records(check_images=True)`` (what the data stage does for ``data=word``) reads each image's
PNG/JPEG header and trailer (existence, format, size, truncation); decoding every image with OpenCV would
also catch corrupt pixel data but costs far more. Prints both per image, projected to the paper's
9,000 images, and their ratio.

    python -m benchmarks.bench_image_checks [--images 200] [--size 640 480]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from deepword.word_format import image_size

PAPER_IMAGES = 9000


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--images", type=int, default=200)
    parser.add_argument("--size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"))
    args = parser.parse_args(argv)
    w, h = args.size
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for ext in (".png", ".jpg"):
            img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (5, 5), 0)
            data = cv2.imencode(ext, img)[1].tobytes()
            for i in range(args.images // 2):
                path = Path(tmp) / f"{i}{ext}"
                path.write_bytes(data)
                paths.append(path)
        start = time.perf_counter()
        for path in paths:
            assert image_size(path) == (w, h)
        header = (time.perf_counter() - start) / len(paths)
        start = time.perf_counter()
        for path in paths:
            assert cv2.imread(str(path)) is not None
        decode = (time.perf_counter() - start) / len(paths)
    print(f"{len(paths)} images {w}x{h} (half PNG, half JPEG)")
    print(f"header check: {header * 1e6:8.0f} us/image  -> {header * PAPER_IMAGES:6.1f} s for {PAPER_IMAGES} images")
    print(f"cv2.imread:   {decode * 1e6:8.0f} us/image  -> {decode * PAPER_IMAGES:6.1f} s for {PAPER_IMAGES} images")
    print(f"ratio decode / header: {decode / header:.0f}x")


if __name__ == "__main__":
    main()
