"""The CLI's static check that lets Hydra compose the config once (pipeline.runmode)."""

from pathlib import Path

import pytest

from pipeline.runmode import is_single_run

CONF = Path(__file__).resolve().parents[2] / "conf"


@pytest.mark.parametrize("overrides, single", [
    ([], True),
    (["profile=smoke", "relation/backbone=resnet18"], True),  # priors' own `mode:` key is not Hydra's
    (["experiment=table1"], False),   # experiment files set hydra.mode: MULTIRUN
    (["+experiment=table2"], False),
    (["hydra.mode=MULTIRUN"], False),
])
def test_project_config(overrides, single):
    assert is_single_run(CONF, "config", overrides) is single


def _write(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def test_primary_config_setting_the_mode_is_not_single(tmp_path):
    conf = _write(tmp_path, {"main.yaml": "x: 1\nhydra:\n  mode: MULTIRUN\n"})
    assert not is_single_run(conf, "main", [])


def test_mode_group_selected_by_a_defaults_list_is_not_single(tmp_path):
    files = {"main.yaml": "defaults:\n  - _self_\n  - sweep: null\n  - size: big\n",
             "sweep/grid.yaml": "# @package _global_\nhydra: {mode: MULTIRUN}\n",
             "size/big.yaml": "n: 2\n"}
    conf = _write(tmp_path, files)
    assert is_single_run(conf, "main", ["size=big"])
    assert not is_single_run(conf, "main", ["sweep=grid"])
    (conf / "size" / "big.yaml").write_text("defaults:\n  - /sweep: grid\nn: 2\n")
    assert not is_single_run(conf, "main", [])


def test_missing_primary_config_leaves_it_to_hydra(tmp_path):
    assert not is_single_run(tmp_path, "nowhere", [])
