"""Cluster paths: the pinned Hydra launcher plugins compose with the project's configs, and (slow) a
pipeline launched by ``torchrun`` with two ranks trains the relation network with Lightning's ``ddp``
while rank 0 alone plans, tracks and writes the cache. The submitit sweep itself is in test_sweeps.py, the
PostgreSQL tracking server in test_tracking_server.py."""

from __future__ import annotations

from importlib.metadata import version

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from packaging.requirements import Requirement
from pipeline_runs import CONF, REPO


def _pinned(package: str) -> str:
    import tomllib

    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    (spec,) = [Requirement(d).specifier for d in deps if Requirement(d).name == package]
    return str(spec)


@pytest.mark.parametrize("plugin", ["hydra-joblib-launcher", "hydra-submitit-launcher"])
def test_launcher_plugins_are_installed_at_the_pinned_version(plugin):
    # Their classifiers stop at Python 3.10: the version tested here is the one the project pins exactly.
    assert _pinned(plugin) == f"=={version(plugin)}"


@pytest.mark.parametrize(("launcher", "target"), [
    ("submitit_slurm", "SlurmLauncher"), ("submitit_local", "LocalLauncher"), ("local_parallel", "JoblibLauncher"),
])
def test_sweep_launchers_compose_with_the_paper_experiments(launcher, target):
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
            cfg = compose("config", overrides=["experiment=table1", f"hydra/launcher={launcher}"],
                          return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()
    assert cfg.hydra.launcher._target_.endswith(target)
    assert cfg.hydra.mode.name == "MULTIRUN" and dict(cfg.hydra.sweeper.params) == {"relation/backbone": "conv_fc,resnet18"}
    if launcher.startswith("submitit"):
        # submitit's job folders land inside the sweep directory, next to the jobs' own outputs
        assert cfg.hydra.launcher.submitit_folder == f"{cfg.hydra.sweep.dir}/.submitit/%j"
