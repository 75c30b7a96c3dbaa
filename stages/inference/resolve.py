"""Which trained artifacts a pipeline run used: from an MLflow run id to its stages' cache entries.

The engine records, for every pipeline invocation, one MLflow parent run (tags ``profile``, ``seed``,
``git_commit``; params = the flattened resolved config, including ``pipeline.cache_dir``) and one child
run per stage (tags ``stage`` and ``cache_key``, cache hits included). A stage's outputs live in the
content-addressed cache at ``<cache_dir>/<stage>/<cache_key>/out``. So:

    run id --(children: tags.stage, tags.cache_key)--> <cache_dir>/export/<key>/out     (ONNX bundle)
                                                       <cache_dir>/evaluate/<key>/out   (baselines.json)

``cache_dir``: ``--cache-dir``, else ``$DEEPWORD_CACHE``, else the run's ``pipeline.cache_dir`` param
(relative paths are taken from the current directory, like the engine's default ``.deepword_cache``).
The default run is the newest FINISHED parent run of the experiment that has an ``export`` child (and a
``detector`` child when detections are needed: sweeps run with ``pipeline.skip=[detector]`` have none).
"""

from __future__ import annotations

import os
from pathlib import Path

DEFAULT_URI = "sqlite:///mlflow.db"
DEFAULT_EXPERIMENT = "deepword"
OUT = "out"


class ResolveError(RuntimeError):
    """The run, its stages or their cache entries cannot be found."""


def _client(uri: str | None):
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=uri or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI)


def _children(client, experiment_id: str, run_id: str) -> dict[str, str]:
    """{stage name: cache key} of a parent run's stage runs."""
    runs = client.search_runs([experiment_id], filter_string=f"tags.mlflow.parentRunId = '{run_id}'",
                              max_results=100)
    return {r.data.tags["stage"]: r.data.tags["cache_key"] for r in runs
            if "stage" in r.data.tags and "cache_key" in r.data.tags}


def _newest_run_with(client, experiment_id: str, stages: set[str]) -> str:
    runs = client.search_runs([experiment_id], filter_string="attributes.status = 'FINISHED'",
                              order_by=["attributes.start_time DESC"], max_results=200)
    for run in runs:
        if "mlflow.parentRunId" not in run.data.tags and stages <= set(_children(client, experiment_id, run.info.run_id)):
            return run.info.run_id
    raise ResolveError(f"no finished pipeline run with the stages {sorted(stages)} in experiment "
                       f"'{DEFAULT_EXPERIMENT}'; run the pipeline first (deepword run) or pass --export DIR")


def stage_dirs(run_id: str | None = None, uri: str | None = None, cache_dir: str | None = None,
               experiment: str = DEFAULT_EXPERIMENT, need_detector: bool = False) -> tuple[str, dict[str, Path]]:
    """(run id, {stage: its output directory}) of the given or the newest finished pipeline run (with a
    detector when ``need_detector``)."""
    client = _client(uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise ResolveError(f"MLflow experiment '{experiment}' not found at {client.tracking_uri}")
    needed = {"export", "detector"} if need_detector else {"export"}
    if run_id is None:
        run_id = _newest_run_with(client, exp.experiment_id, needed)
    try:
        run = client.get_run(run_id)
    except Exception as exc:  # MlflowException: unknown id
        raise ResolveError(f"MLflow run {run_id!r} not found at {client.tracking_uri}: {exc}") from None
    keys = _children(client, exp.experiment_id, run_id)
    if not keys:
        raise ResolveError(f"run {run_id} has no stage runs: not a pipeline run (pass the parent run's id)")
    if need_detector and "detector" not in keys:
        raise ResolveError(f"run {run_id} has no detector (it ran with pipeline.skip=[detector]): pass the --run "
                           "of a pipeline run with one, or use --dataset without --detect")
    root = Path(cache_dir or os.environ.get("DEEPWORD_CACHE") or run.data.params.get("pipeline.cache_dir")
                or ".deepword_cache").expanduser()
    dirs = {}
    for stage, key in keys.items():
        path = root / stage / key / OUT
        if path.is_dir():
            dirs[stage] = path
    if "export" not in dirs:
        raise ResolveError(f"run {run_id}: the export stage's cache entry {root / 'export' / keys.get('export', '?')} "
                           "is not there (another cache directory? pass --cache-dir, or re-run the pipeline)")
    return run_id, dirs
