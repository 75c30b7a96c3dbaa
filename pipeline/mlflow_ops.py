"""The MLflow operations the engine performs, on an ``MlflowClient`` with its batch APIs.

Used either in-process or inside the tracking worker (``pipeline.mlflow_worker``); arguments and
results are plain JSON values so both paths share this one implementation. ``mlflow`` is imported
only when an instance is created: it is the slowest import of a no-op run.
"""

from __future__ import annotations

import contextlib
import fcntl
import time
from pathlib import Path

MAX_PARAMS_PER_BATCH = 100
MAX_METRICS_PER_BATCH = 1000
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
EXPERIMENT_KIND = "custom_model_development"
DATASET_DIGEST_CHARS = 36  # the length of MLflow's dataset digest column


@contextlib.contextmanager
def _sqlite_init_lock(uri: str):
    """MLflow creates and migrates a new sqlite store's tables on first use, and two processes doing that
    at once fail ("duplicate column name"): pipelines started together take turns opening the store."""
    if not uri.startswith("sqlite:///"):
        yield
        return
    with open(f"{uri.removeprefix('sqlite:///')}.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)  # released when the file closes
        yield


class MlflowOps:
    def __init__(self, uri: str, experiment: str):
        from mlflow.tracking import MlflowClient

        self.uri = uri
        with _sqlite_init_lock(uri):
            self.client = MlflowClient(tracking_uri=uri)
            self.experiment_id = self._experiment_id(experiment)

    def _experiment_id(self, name: str) -> str:
        found = self.client.get_experiment_by_name(name)
        if found is not None:
            if EXPERIMENT_KIND_TAG not in found.tags:  # created before the engine set it, or by another tool
                self.client.set_experiment_tag(found.experiment_id, EXPERIMENT_KIND_TAG, EXPERIMENT_KIND)
            return found.experiment_id
        try:
            # The kind makes the MLflow 3 UI open the experiment on its training runs, not on GenAI traces.
            return self.client.create_experiment(name, tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND})
        except Exception:  # a concurrent pipeline created it first
            found = self.client.get_experiment_by_name(name)
            if found is None:
                raise
            return found.experiment_id

    def create_run(self, run_name: str, tags: dict[str, str], parent_id: str | None = None) -> str:
        tags = dict(tags)
        if parent_id:
            tags["mlflow.parentRunId"] = parent_id
        run = self.client.create_run(self.experiment_id, run_name=run_name, tags=tags)
        return run.info.run_id

    def log(self, run_id: str, metrics: dict | None = None, params: dict | None = None,
            tags: dict | None = None) -> None:
        from mlflow.entities import Metric, Param, RunTag

        now = int(time.time() * 1000)
        metric_list = [Metric(k, float(v), now, 0) for k, v in (metrics or {}).items()]
        param_list = [Param(k, str(v)) for k, v in (params or {}).items()]
        tag_list = [RunTag(k, str(v)) for k, v in (tags or {}).items()]
        # One request when it fits; MLflow caps a batch at 100 params and 1000 metrics.
        while metric_list or param_list or tag_list:
            self.client.log_batch(
                run_id,
                metrics=metric_list[:MAX_METRICS_PER_BATCH],
                params=param_list[:MAX_PARAMS_PER_BATCH],
                tags=tag_list[:100],
            )
            metric_list = metric_list[MAX_METRICS_PER_BATCH:]
            param_list = param_list[MAX_PARAMS_PER_BATCH:]
            tag_list = tag_list[100:]

    def log_artifacts(self, run_id: str, directory: str) -> None:
        if Path(directory).is_dir() and any(Path(directory).iterdir()):
            self.client.log_artifacts(run_id, directory)

    def log_dataset(self, run_id: str, name: str, digest: str, source: str) -> None:
        """Record a dataset as an input of the run (the UI's Dataset column): its ``digest`` identifies the
        content (MLflow keeps 36 characters of it), ``source`` says where it is."""
        from mlflow.entities import Dataset, DatasetInput

        dataset = Dataset(name=name, digest=digest[:DATASET_DIGEST_CHARS], source_type="local", source=source)
        try:
            self.client.log_inputs(run_id, datasets=[DatasetInput(dataset=dataset)])
        except Exception as exc:
            # MLflow looks the dataset up, then inserts it: a concurrent pipeline logging the same dataset
            # can insert it in between. The second attempt finds that row and links it to this run.
            if "UNIQUE constraint" not in str(exc) and "unique constraint" not in str(exc).lower():
                raise
            self.client.log_inputs(run_id, datasets=[DatasetInput(dataset=dataset)])

    def find_recorded(self, digest: str) -> dict | None:
        """The newest finished parent run tagged ``pipeline.run_digest = digest`` with its stages' child runs, as
        ``RecordedRun.to_json`` (``pipeline.run_record``: what the engine asks when it cannot read the store itself)."""
        from mlflow.entities import ViewType

        from pipeline.run_record import DIGEST_TAG, PARENT_TAG, STAGE_TAG, RecordedRun

        found = self.client.search_runs(
            [self.experiment_id], filter_string=f"tags.`{DIGEST_TAG}` = '{digest}' and attributes.status = 'FINISHED'",
            run_view_type=ViewType.ACTIVE_ONLY, max_results=1, order_by=["attributes.start_time DESC"])
        if not found:
            return None
        run = found[0]
        children = self.client.search_runs([self.experiment_id], filter_string=f"tags.`{PARENT_TAG}` = '{run.info.run_id}'",
                                           run_view_type=ViewType.ALL, max_results=1000)
        return RecordedRun(run.info.run_id, run.info.run_name or "", int(run.info.start_time),
                           {c.data.tags[STAGE_TAG]: c.info.run_id for c in children if STAGE_TAG in c.data.tags}
                           ).to_json()

    def end(self, run_id: str, status: str = "FINISHED") -> None:
        self.client.set_terminated(run_id, status=status)
