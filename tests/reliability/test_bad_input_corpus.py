"""Every bad input of the corpus gives a DatasetError naming file, line and field (docs/design.md §4, §10)."""

from __future__ import annotations

import filecmp
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from deepword.word_format import (
    DatasetError,
    check_image_files,
    image_size,
    load_image,
    open_dataset,
    read_records,
)
from tests.reliability.make_corpus import CASES, CORPUS, Dataset, build_corpus, write_dataset

CASE_NAMES = sorted(CASES)


def expected(case: str) -> dict:
    return json.loads((CORPUS / case / "expected.json").read_text())


def cases_found_by(*layers: str) -> list[str]:
    return [c for c in CASE_NAMES if CASES[c][4] in layers]


def validate_like_a_stage(root: Path) -> None:
    """What the data stage and the image-reading stages do: read with image checks, then decode."""
    for rec in read_records(root / "labels.jsonl", check_images=True):
        load_image(root, rec)


def assert_located(err: DatasetError, case: str) -> None:
    exp = expected(case)
    assert Path(err.file).resolve() == (CORPUS / case / "labels.jsonl").resolve()
    assert err.line == exp["line"]
    assert err.field == exp["field"]
    assert exp["message"] in err.message
    where = f"labels.jsonl:{exp['line']}" if exp["line"] is not None else "labels.jsonl"
    assert where in str(err) and f"field '{exp['field']}'" in str(err)


def test_committed_corpus_is_what_make_corpus_writes(tmp_path):
    build_corpus(tmp_path / "corpus")
    cmp = filecmp.dircmp(CORPUS, tmp_path / "corpus")
    stack, differences = [cmp], []
    while stack:
        d = stack.pop()
        differences += d.left_only + d.right_only + d.diff_files
        stack += d.subdirs.values()
    assert differences == [], "run tests/reliability/make_corpus.py and commit the corpus"
    for case in CASE_NAMES:  # byte-level, not just stat-level
        for path in (CORPUS / case).rglob("*"):
            if path.is_file():
                assert path.read_bytes() == (tmp_path / "corpus" / case / path.relative_to(CORPUS / case)).read_bytes()


def test_corpus_without_a_fault_reads_and_decodes_cleanly(tmp_path):
    root = write_dataset(Dataset(), tmp_path / "clean")
    validate_like_a_stage(root)
    assert len(read_records(root / "labels.jsonl")) == 2


@pytest.mark.parametrize("case", CASE_NAMES)
def test_bad_input_gives_dataset_error_naming_file_line_and_field(case):
    with pytest.raises(DatasetError) as info:
        validate_like_a_stage(CORPUS / case)
    assert_located(info.value, case)


@pytest.mark.parametrize("case", cases_found_by("labels"))
def test_label_faults_are_found_while_reading_labels_without_images(case):
    with pytest.raises(DatasetError) as info:
        read_records(CORPUS / case / "labels.jsonl")
    assert_located(info.value, case)


@pytest.mark.parametrize("case", cases_found_by("files"))
def test_image_file_faults_are_found_from_headers_before_any_decoding(case, monkeypatch):
    def no_decoding(*args, **kwargs):
        raise AssertionError("the header check must not decode images")

    monkeypatch.setattr(cv2, "imread", no_decoding)
    records = read_records(CORPUS / case / "labels.jsonl")  # labels themselves are fine
    with pytest.raises(DatasetError) as info:
        read_records(CORPUS / case / "labels.jsonl", check_images=True)
    assert_located(info.value, case)
    with pytest.raises(DatasetError) as info:
        check_image_files(CORPUS / case, records)
    assert_located(info.value, case)


@pytest.mark.parametrize("case", cases_found_by("files", "decode"))
def test_load_image_reports_image_faults_at_the_records_line(case):
    bad = read_records(CORPUS / case / "labels.jsonl")[1]
    with pytest.raises(DatasetError) as info:
        load_image(CORPUS / case, bad)
    assert_located(info.value, case)


def test_truncated_jpeg_is_refused_although_opencv_decodes_it(tmp_path):
    ds = Dataset()
    root = write_dataset(ds, tmp_path / "jpeg")
    rec = read_records(root / "labels.jsonl")[1]
    img = np.random.default_rng(0).integers(0, 255, (rec.height, rec.width, 3), dtype=np.uint8)
    ok, data = cv2.imencode(".jpg", img)
    jpg = root / rec.image
    jpg.write_bytes(data.tobytes()[:-40])
    assert cv2.imread(str(jpg)) is not None  # the premise: OpenCV only warns "Premature end of JPEG file"
    with pytest.raises(DatasetError) as info:
        load_image(root, rec)
    assert (info.value.line, info.value.field) == (2, "image") and "truncated" in info.value.message


@pytest.mark.parametrize("ext, params", [(".png", []), (".jpg", []),
                                         (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])])
def test_image_size_reads_width_and_height_from_png_and_jpeg_headers(tmp_path, ext, params):
    img = np.zeros((37, 53, 3), dtype=np.uint8)
    path = tmp_path / f"a{ext}"
    assert cv2.imwrite(str(path), img, params)
    assert image_size(path) == (53, 37)


def test_symlink_leaving_the_root_is_refused(tmp_path):
    root = write_dataset(Dataset(), tmp_path / "root")
    outside = tmp_path / "outside.png"
    target = root / "images" / "left" / "000001.png"
    outside.write_bytes(target.read_bytes())
    target.unlink()
    os.symlink(outside, target)
    with pytest.raises(DatasetError) as info:
        read_records(root / "labels.jsonl")
    assert (info.value.line, info.value.field) == (2, "image") and "leaves the dataset root" in info.value.message


def test_missing_labels_file_names_the_file(tmp_path):
    with pytest.raises(DatasetError) as info:
        read_records(tmp_path / "labels.jsonl")
    assert info.value.file.endswith("labels.jsonl") and info.value.line is None and info.value.field == "<file>"


def test_data_dir_without_index_is_a_dataset_error_not_a_traceback(tmp_path):
    with pytest.raises(DatasetError) as info:
        open_dataset(tmp_path)
    assert info.value.file.endswith("dataset.json") and info.value.field == "<file>"
