"""``python -m stages.tables.adapt_base``: print the MLflow run id of the newest finished *default* run, the one
``experiment=adapt``'s finetune recipe starts from (``make adapt`` passes it as ``adapt.base_run``; docs/adapt.md).

A default run: a plain ``make pipeline`` of the profile (quick unless ``--profile``): no sweep (no
``experiment_name``), ``data=synword``, ``init=scratch``, the relation network, detector and data settings of the
default configuration composed under that profile (training threads, loader workers and the ``relation.train``
budget aside, as for the paper tables' rows), and evaluated end to end on the held-out test set. Exits 1 with a
message when there is none.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys

from pipeline.runs import RunRecord, load_runs
from pipeline.tracker import flatten_params
from stages.tables.rows import CONF, NOT_DEFINING

DEFINING = ("relation.", "detector.", "data.")
# The rule that sizes the detector's epochs to a host (its minutes and floor) chose a run's epochs, which define it;
# the rule itself does not (a run sized under an earlier floor with the same epochs is the same run). max_epochs stays:
# a run pinned to it is the default run on a slow host (``_as_defined``).
NOT_DEFINING_HERE = NOT_DEFINING | {"detector.num_workers", "relation.train.num_workers", "data.workers",
                                    "detector.sizing.minutes", "detector.sizing.min_epochs"}
NEEDED_METRICS = ("detector.shift.ap50.vehicle", "eval.shift.gt.deepword.mixed.pair_f1")


@functools.cache
def default_definition(profile: str) -> dict[str, str]:
    """The flattened parameters a default run of ``profile`` has (``DEFINING`` prefixes)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf


    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
            cfg = OmegaConf.to_container(compose("config", overrides=[f"profile={profile}"]), resolve=True)
    finally:
        GlobalHydra.instance().clear()
    return {k: v for k, v in flatten_params(cfg).items() if k.startswith(DEFINING) and k not in NOT_DEFINING_HERE}


def is_default_run(run: RunRecord, profile: str) -> bool:
    if run.tags.get("profile") != profile or run.param("experiment_name") is not None:
        return False
    if run.param("data.name") != "synword" or run.param("init.source") not in (None, "scratch"):
        return False
    if not all(k in run.metrics for k in NEEDED_METRICS):
        return False
    definition = default_definition(profile)
    return all(_as_defined(run, k, v, definition) for k, v in definition.items())


def _as_defined(run: RunRecord, key: str, value: str, definition: dict[str, str]) -> bool:
    """The run's param is the profile's value, or the value the plan sized the profile's ``auto`` to on the run's host
    (pipeline.sizing: logged as ``sized.<key>`` beside the config's ``<key>``), or, set outright, the most that ``auto``
    may size it to (``<stage>.sizing.max_<name>`` of the profile: what a host fast enough gets, the budget a run pins
    to compare with the default run on a slower or busy host)."""
    given = run.params.get(key, value)
    if given == value or (value == "auto" and run.params.get(f"sized.{key}") == given):
        return True
    stage, _, name = key.rpartition(".")
    return value == "auto" and definition.get(f"{stage}.sizing.max_{name}") == given


def newest_default_run(runs: list[RunRecord], profile: str) -> RunRecord | None:
    """``runs`` newest first (``pipeline.runs.load_runs``)."""
    return next((r for r in runs if is_default_run(r, profile)), None)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m stages.tables.adapt_base", description=__doc__.split("\n")[0])
    parser.add_argument("--tracking-uri", default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"))
    parser.add_argument("--experiment", default="deepword")
    parser.add_argument("--profile", default="quick")
    args = parser.parse_args(argv)
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=args.tracking_uri)
    found = client.get_experiment_by_name(args.experiment)
    run = None
    if found is not None:
        run = newest_default_run(load_runs(client, found.experiment_id, args.profile), args.profile)
    if run is None:
        sys.exit(f"error: no finished default run (profile {args.profile}, data=synword, init=scratch, evaluated on "
                 f"the held-out test set) in experiment {args.experiment!r} at {args.tracking_uri}: run `make pipeline` "
                 f"first{'' if args.profile == 'quick' else f' (ARGS=profile={args.profile})'}, or give its id: "
                 "make adapt BASE_RUN=<run id>")
    print(run.run_id)


if __name__ == "__main__":
    main()
