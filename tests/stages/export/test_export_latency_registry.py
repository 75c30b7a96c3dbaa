"""Latency helpers and the MLflow model registry of the exported models."""

import numpy as np
import pytest

from stages.export.latency import batches, graph_batches, median_ms


def test_batches_cycle_through_images_and_concatenate_along_batch():
    feeds = [{"x": np.full((1, 2), i)} for i in range(3)]
    out = batches(feeds, 2)
    assert [f["x"][:, 0].tolist() for f in out] == [[0, 1], [2, 0]]


def test_graph_batches_pad_each_batch_to_its_largest_graph_or_to_n():
    from deepword.relation_graph import ImageGraph

    def graph(k: int) -> ImageGraph:
        return ImageGraph(crops=np.full((k, 3, 4, 4), k, np.uint8), coords=np.ones((k, 4), np.float32),
                          classes=np.zeros(k, np.int8), valid=np.ones(k, bool), adj=np.eye(k, dtype=np.float32),
                          cand=np.zeros((k, k), bool))

    graphs = [graph(k) for k in (2, 5, 3)]
    out = graph_batches(graphs, 4, 2)  # (2, 5) and (3, 2): the last batch cycles back to the first graph
    assert [f["crops"].shape[:2] for f in out] == [(2, 5), (2, 3)]
    assert out[1]["crops"][1, :2].min() == 2 and out[1]["coords"][1, 2:].max() == 0  # padding: all-zero boxes
    assert [f["adj"].shape for f in graph_batches(graphs, 4, 1, n=6)] == [(1, 6, 6)] * 3


def test_median_ms_runs_warmup_then_timed_calls():
    calls = []
    ms = median_ms(calls.append, runs=5, warmup=2)
    assert calls == [0, 1, 0, 1, 2, 3, 4] and ms >= 0
    with pytest.raises(ValueError, match="runs"):
        median_ms(calls.append, runs=0, warmup=0)


@pytest.mark.slow  # MLflow: sqlite store + two logged models (~20-30 s on 2 busy cores)
def test_register_models_logs_and_registers_both_with_metrics(exported, tmp_path, monkeypatch):
    from mlflow.tracking import MlflowClient

    from deepword.inference.runtime import DETECTOR_FILE, RELATION_FILES
    from stages.export.registry import REGISTERED_NAMES, register_models

    monkeypatch.chdir(tmp_path)  # artifacts of the sqlite store go under the working directory
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    run_id = client.create_run(client.create_experiment("deepword")).info.run_id
    out, metrics = exported
    per_model = {"relation": {"export.relation.ms_per_img_b1": metrics["export.relation.ms_per_img_b1"]},
                 "detector": {"export.detector.size_mb": metrics["export.detector.size_mb"]}}
    registered = register_models((uri, run_id), {"relation": out / RELATION_FILES["static"],
                                                 "detector": out / DETECTOR_FILE}, per_model)
    for name in ("relation", "detector"):
        version = client.get_model_version(REGISTERED_NAMES[name], registered[name]["version"])
        assert version.run_id == run_id
        key = next(iter(per_model[name]))
        assert float(version.tags[key]) == pytest.approx(per_model[name][key], rel=1e-5)
