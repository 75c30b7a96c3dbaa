"""Queries of the pipeline's runs in MLflow, for tools that tabulate them: the finished parent runs (one per
``python -m pipeline`` invocation, every stage's metrics on it, docs/design.md §8) with their flattened
parameters, metrics and tags. Knows nothing about what the runs computed."""

from __future__ import annotations

import json
from dataclasses import dataclass

PARENT_TAG = "mlflow.parentRunId"


@dataclass
class RunRecord:
    run_id: str
    name: str
    start_time: int           # milliseconds since the epoch
    params: dict[str, str]    # the flattened resolved config (pipeline.tracker.flatten_params)
    metrics: dict[str, float]
    tags: dict[str, str]

    def param(self, key: str):
        """A flattened config value back to Python (the engine logs non-strings as JSON); None if absent."""
        return param_value(self.params.get(key))


def param_value(text: str | None):
    if text is None:
        return None
    try:
        return json.loads(text)
    except ValueError:
        return text


def load_runs(client, experiment_id: str, profile: str | None = None,
              exclude_tags: dict[str, str] | None = None) -> list[RunRecord]:
    """Finished pipeline parent runs, newest first: stage child runs are left out, and so are runs carrying
    any of ``exclude_tags`` (e.g. the runs a tabulating tool logs itself); with ``profile``, only runs tagged
    with that profile."""
    from mlflow.entities import ViewType

    exclude_tags = exclude_tags or {}
    runs, token = [], None
    while True:
        page = client.search_runs([experiment_id], filter_string="attributes.status = 'FINISHED'",
                                  run_view_type=ViewType.ACTIVE_ONLY, max_results=1000,
                                  order_by=["attributes.start_time DESC"], page_token=token)
        for r in page:
            tags = r.data.tags
            if PARENT_TAG in tags or any(tags.get(k) == v for k, v in exclude_tags.items()):
                continue
            if profile is not None and tags.get("profile") != profile:
                continue
            runs.append(RunRecord(r.info.run_id, r.info.run_name or "", r.info.start_time, dict(r.data.params),
                                  dict(r.data.metrics), dict(tags)))
        token = page.token
        if not token:
            return runs
