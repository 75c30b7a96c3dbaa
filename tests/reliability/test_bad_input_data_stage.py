"""The data stage on a bad WORD-style dataset (``data=word``) stops with the reader's file/line/field error
before anything downstream runs and before writing its outputs."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from deepword.word_format import DatasetError
from stages.data.stage import run as data_stage
from tests.reliability.make_corpus import CASES, CORPUS, Dataset, write_dataset

REPO = Path(__file__).resolve().parents[2]
UP_FRONT = sorted(c for c in CASES if CASES[c][4] in ("labels", "files"))


@functools.cache
def _word_data_cfg() -> dict:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["data=word", "data.root=ROOT", "profile=smoke"])
    return {"data": OmegaConf.to_container(cfg.data), "seed": cfg.seed}


def data_cfg(root: Path):
    """The data stage's config subtree for ``data=word data.root=<root>`` (composed once, then re-rooted)."""
    cfg = OmegaConf.create(_word_data_cfg())
    cfg.data.root = str(root)
    return OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))


@pytest.mark.parametrize("case", UP_FRONT)
def test_data_stage_refuses_bad_dataset_naming_file_line_and_field(case, tmp_path):
    exp = json.loads((CORPUS / case / "expected.json").read_text())
    with pytest.raises(DatasetError) as info:
        data_stage(data_cfg(CORPUS / case), {}, tmp_path)
    err = info.value
    assert Path(err.file).resolve() == (CORPUS / case / "labels.jsonl").resolve()
    assert (err.line, err.field) == (exp["line"], exp["field"]) and exp["message"] in err.message
    assert not (tmp_path / "dataset.json").exists()


def test_data_stage_accepts_the_same_dataset_without_a_fault(tmp_path):
    root = write_dataset(Dataset(), tmp_path / "clean")
    out = tmp_path / "out"
    out.mkdir()
    metrics = data_stage(data_cfg(root), {}, out)
    assert (out / "dataset.json").is_file() and sum(metrics[f"data.{s}.images"] for s in ("train", "val", "test")) == 2
