"""Shared fixture of the data stage tests: one generated sample."""

import pytest

from tests.stages.data.data_helpers import synword_cfg


@pytest.fixture(scope="session")
def synword_sample(tmp_path_factory):
    """12 frames (48 renders at 320x240), generated once for the label tests."""
    from stages.data.synword import generate

    out = tmp_path_factory.mktemp("synword")
    records = generate(synword_cfg(frames=12), seed=7, out_dir=out, workers=1, progress=False)
    return out, records
