"""The exported models in the MLflow model registry: ``mlflow.onnx.log_model`` into the export stage's
child run and a registered version of ``deepword-relation`` / ``deepword-detector``, tagged with the
run's metrics (and the metrics linked to the logged model, so the MLflow UI shows them side by side).
Only called inside a pipeline run (``pipeline.tracking.stage_run_info()`` is not None)."""

from __future__ import annotations

from pathlib import Path

REGISTERED_NAMES = {"relation": "deepword-relation", "detector": "deepword-detector"}


def register_models(tracking: tuple[str, str], models: dict[str, Path], metrics: dict[str, dict[str, float]]) -> dict:
    """Log and register each ``models[name]`` (an ONNX file) with ``metrics[name]``; returns
    {name: {"registered_model": ..., "version": ..., "model_uri": ...}}."""
    import mlflow
    import mlflow.onnx
    import onnx
    from mlflow.tracking import MlflowClient

    uri, run_id = tracking
    mlflow.set_tracking_uri(uri)
    client = MlflowClient(tracking_uri=uri)
    out = {}
    with mlflow.start_run(run_id=run_id):
        for name, path in models.items():
            registered = REGISTERED_NAMES[name]
            info = mlflow.onnx.log_model(onnx.load(str(path)), name=name, registered_model_name=registered,
                                         save_as_external_data=False, pip_requirements=["onnx", "onnxruntime"])
            if metrics.get(name):
                mlflow.log_metrics(metrics[name], model_id=info.model_id)
            version = str(info.registered_model_version)
            for key, value in metrics.get(name, {}).items():
                client.set_model_version_tag(registered, version, key, f"{value:.6g}")
            client.set_model_version_tag(registered, version, "file", path.name)
            out[name] = {"registered_model": registered, "version": version, "model_uri": info.model_uri}
    return out
