"""Image files of a dataset: sizes and completeness from PNG/JPEG headers and trailers (no decoding, cheap
enough for every image up front), and loading an image checked against its record."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deepword.word_format.record import DatasetError, Record

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_TRAILER = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the empty IEND chunk every complete PNG ends with
_JPEG_SOI, _JPEG_EOI = b"\xff\xd8", b"\xff\xd9"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_TAIL = 1024  # the end-of-image marker must lie this close to the end (some writers pad after it)


def _jpeg_size(fh) -> tuple[int, int]:
    """Walk the JPEG marker segments up to the first start-of-frame and read its width and height."""
    fh.seek(2)
    while True:
        byte = fh.read(1)
        if byte != b"\xff":
            raise ValueError("JPEG marker expected: the file is corrupt or truncated")
        marker = fh.read(1)
        while marker == b"\xff":  # fill bytes
            marker = fh.read(1)
        if not marker:
            raise ValueError("JPEG header is truncated")
        m = marker[0]
        if m == 0x01 or 0xD0 <= m <= 0xD7:  # markers without a length field
            continue
        length_bytes = fh.read(2)
        if len(length_bytes) < 2:
            raise ValueError("JPEG header is truncated")
        length = int.from_bytes(length_bytes, "big")
        if m in _JPEG_SOF:
            sof = fh.read(5)
            if len(sof) < 5:
                raise ValueError("JPEG header is truncated")
            return int.from_bytes(sof[3:5], "big"), int.from_bytes(sof[1:3], "big")
        if m in (0xD9, 0xDA) or length < 2:
            raise ValueError("JPEG has no frame header before its image data")
        fh.seek(length - 2, os.SEEK_CUR)


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a PNG or JPEG file from its header, and a check that the file is complete
    (PNG: ends with IEND; JPEG: an end-of-image marker in its last KiB). Reads a few hundred bytes, decodes
    nothing: cheap enough to check every image of a dataset up front. Raises ValueError saying what is wrong."""
    with open(path, "rb") as fh:
        head = fh.read(24)
        size = fh.seek(0, os.SEEK_END)
        if head.startswith(_PNG_SIGNATURE):
            if len(head) < 24 or head[12:16] != b"IHDR":
                raise ValueError("PNG header is truncated or corrupt")
            wh = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            fh.seek(max(size - len(_PNG_TRAILER), 0))
            if fh.read() != _PNG_TRAILER:
                raise ValueError("PNG is truncated (it does not end with an IEND chunk)")
        elif head.startswith(_JPEG_SOI):
            wh = _jpeg_size(fh)
            fh.seek(max(size - _JPEG_TAIL, 0))
            if _JPEG_EOI not in fh.read():
                raise ValueError("JPEG is truncated (no end-of-image marker at its end)")
        else:
            raise ValueError("not a PNG or JPEG file")
    if min(wh) <= 0:
        raise ValueError(f"header gives an empty image size {wh[0]}x{wh[1]}")
    return wh


def check_image_file(root: str | os.PathLike, record: Record) -> None:
    """Check that the record's image exists, is a complete PNG/JPEG and has the record's size, from its
    header only; raise DatasetError with the record's file and line."""
    path = Path(root) / record.image
    file, line = record.source or (str(path), None)
    if not path.is_file():
        raise DatasetError(file, line, "image", f"image file {path} not found")
    try:
        w, h = image_size(path)
    except OSError as exc:
        raise DatasetError(file, line, "image", f"image file {path} cannot be read: {exc.strerror}") from None
    except ValueError as exc:
        raise DatasetError(file, line, "image", f"image file {path}: {exc}") from None
    if (w, h) != (record.width, record.height):
        fld = "width" if w != record.width else "height"
        raise DatasetError(file, line, fld, f"image {path} is {w}x{h}, the record says {record.width}x{record.height}")


def check_image_files(root: str | os.PathLike, records: list[Record]) -> None:
    """check_image_file for every record, stopping at the first problem."""
    for rec in records:
        check_image_file(root, rec)


def load_image(root: str | os.PathLike, record: Record) -> np.ndarray:
    """The record's image as an RGB uint8 array, checked against the record's width and height.
    The header check comes first because OpenCV decodes a truncated JPEG without complaint."""
    import cv2  # deferred: keeps the reader importable without OpenCV's load time

    check_image_file(root, record)
    path = Path(root) / record.image
    file, line = record.source or (str(path), None)
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(file, line, "image", f"image file {path} is corrupt or not an image")
    h, w = bgr.shape[:2]
    if (w, h) != (record.width, record.height):
        fld = "width" if w != record.width else "height"
        raise DatasetError(file, line, fld, f"image {path} is {w}x{h}, the record says {record.width}x{record.height}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
