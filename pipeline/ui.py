"""``make ui``: the MLflow UI over the pipeline's tracking store, bound to 127.0.0.1, and the address of the
experiment's runs table.

MLflow 3's UI chooses an experiment's landing page from the browser's "GenAI / Model training" switch
(remembered per browser, GenAI by default) as well as from the experiment's kind tag, so a browser that
never flipped the switch opens even a model-training experiment on the GenAI overview. The address printed
here carries ``workflowType=machine_learning``, which opens the experiment on its runs table.

MLflow's job runner (GenAI judges, trace roll-ups: nothing this project's runs use) is off unless the environment
turns it on: ``mlflow ui`` otherwise starts six ``huey_consumer`` processes beside the server, each importing
MLflow (~20 s of CPU on a 2-core host before the UI answers)."""

from __future__ import annotations

import argparse
import os
import sys

WORKFLOW_PARAM = "workflowType=machine_learning"
# The environment setting that keeps ``mlflow ui`` / ``mlflow server`` from starting MLflow's job runner.
NO_JOB_RUNNER = ("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")


def experiment_url(base: str, tracking_uri: str, experiment: str) -> str:
    """The UI address of ``experiment``'s landing page in the model-training view (the experiments list when
    the experiment does not exist yet)."""
    from mlflow.tracking import MlflowClient

    found = MlflowClient(tracking_uri=tracking_uri).get_experiment_by_name(experiment)
    if found is None:
        return f"{base}/#/experiments?{WORKFLOW_PARAM}"
    return f"{base}/#/experiments/{found.experiment_id}?{WORKFLOW_PARAM}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.ui", description=__doc__.split("\n")[0])
    parser.add_argument("--backend-store-uri", default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"))
    parser.add_argument("--experiment", default="deepword")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=5000)
    args = parser.parse_args(argv)
    url = experiment_url(f"http://{args.host}:{args.port}", args.backend_store_uri, args.experiment)
    print(f"The runs of experiment '{args.experiment}': {url}", file=sys.stderr, flush=True)
    mlflow = os.path.join(os.path.dirname(sys.executable), "mlflow")
    os.environ.setdefault(NO_JOB_RUNNER[0], NO_JOB_RUNNER[1])
    os.execv(mlflow, [mlflow, "ui", "--backend-store-uri", args.backend_store_uri, "--host", args.host,
                      "--port", str(args.port)])


if __name__ == "__main__":
    main()
