"""Latency of the exported models like the paper's Tables 1-2, beside the paper's embedded row.

    python -m benchmarks.bench_latency [--threads 2] [--runs 50] [--warmup 10]

What it times: a *freshly initialised* relation model and detector of the **default config**
(conf/relation: conv_fc_56_ex4, one network or the ensemble of ``relation.ensemble`` as the stage ships it;
conf/detector), exported exactly as the export stage exports them
(``stages.export.onnx_export``) and timed by the export stage's own functions
(``stages.export.stage.relation_latency`` / ``detector_latency``), so the figures are the stage's
metrics. Weights do not change the cost of these graphs (no data-dependent control flow besides
skipping padded objects), so the figures hold for a trained model too and the benchmark needs no
pipeline run. The relation inputs are random graphs with the object counts of the first 50 test images
of a quick-profile run (``TEST_OBJECT_COUNTS``): batch 1 at each image's real count, batch 10 = 10
consecutive images padded to the largest of them; the static model padded to max_objects. onnxruntime
and PyTorch eager run in this process on the same inputs with the same intra-op thread count: the ratio
is the figure to trust on a shared machine, the absolute times depend on the load. The "CPU time" rows
(one thread, that thread's CPU time) estimate the cost without the machine's other load.
The trained model's figures of a pipeline run are the export stage's metrics (artifacts/latency.md).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from deepword.paper import DSP_LATENCY

CONF = Path(__file__).resolve().parent.parent / "conf"
TARGET = {"ms_per_img_b1": 1.6, "ms_per_10img_b10": 13.1}  # the latency targets, onnxruntime on 2 CPU cores
TARGET_SPEEDUP = 1.5  # onnxruntime vs PyTorch eager, same run
# Object counts of the first 50 test images of the quick profile (seed 42; 2-30 objects, mean 13.3).
TEST_OBJECT_COUNTS = (19, 21, 28, 12, 7, 30, 8, 22, 7, 20, 8, 7, 27, 9, 2, 6, 22, 28, 15, 15, 20, 18, 14, 5, 5,
                      3, 14, 4, 11, 4, 7, 18, 6, 12, 7, 8, 24, 3, 9, 30, 23, 10, 12, 17, 15, 15, 5, 22, 4, 7)


INT8_OPS = ["MatMul", "Gemm"]   # the operators quantised to INT8, as conf/export/default.yaml's int8.op_types


def default_configs() -> tuple[dict, dict]:
    """The relation and detector sections of the default config, composed from conf/ like the pipeline."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose(config_name="config")
    return OmegaConf.to_container(cfg.relation, resolve=True), OmegaConf.to_container(cfg.detector, resolve=True)


def random_graphs(counts, size: int, seed: int = 0) -> list:
    from deepword.relation_graph import ImageGraph

    rng = np.random.default_rng(seed)
    graphs = []
    for n in counts:
        classes = (np.arange(n) % 3 != 0).astype(np.int8)  # a third vehicles, the rest wheels
        cand = classes[:, None] + classes[None, :] >= 1
        np.fill_diagonal(cand, False)
        adj = np.where(cand, rng.random((n, n)), 0).astype(np.float32)
        np.fill_diagonal(adj, 1.0)
        graphs.append(ImageGraph(crops=rng.integers(0, 256, (n, 3, size, size), dtype=np.uint8),
                                 coords=rng.random((n, 4), dtype=np.float32), classes=classes,
                                 valid=np.ones(n, bool), adj=adj, cand=cand))
    return graphs


def default_relation_model(rel):
    """What the relation stage ships for the ``relation`` config: one network, or (``relation.ensemble`` > 1 without
    ``relation.distill``) the ensemble of that many, exported as one graph."""
    from stages.relation.distill import DistillConfig
    from stages.relation.model import ModelConfig, RelationEnsemble, RelationNet

    cfg, members = ModelConfig.from_cfg(rel), int(rel.get("ensemble", 1))
    if members > 1 and not DistillConfig.from_cfg(rel.get("distill")).ships_student(members):
        return RelationEnsemble([RelationNet(cfg) for _ in range(members)]).eval()
    return RelationNet(cfg).eval()


def measure(threads: int, runs: int, warmup: int) -> dict[str, float]:
    import torch
    from omegaconf import OmegaConf

    from deepword.inference.runtime import DETECTOR_FILE, RELATION_FILES
    from deepword.relation_graph import InputConfig
    from stages.detector.model import build_centernet, model_config
    from stages.export.onnx_export import export_detector
    from stages.export.stage import detector_latency, export_relation_models, relation_latency, size_mb
    from stages.relation.model import count_parameters

    rel, det = default_configs()
    torch.manual_seed(0)
    net = default_relation_model(OmegaConf.create(rel))
    in_cfg = InputConfig.from_cfg(OmegaConf.create(rel))
    det_cfg = model_config(det)
    det_net = build_centernet(det_cfg).eval()
    size, n = in_cfg.input_size, in_cfg.max_objects
    graphs = random_graphs(TEST_OBJECT_COUNTS, size)
    images = np.random.default_rng(0).normal(size=(10, 3, det_cfg["input_height"], det_cfg["input_width"]))
    lat = OmegaConf.create({"threads": threads, "runs": runs, "warmup": warmup})
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        export_relation_models(net, out, size, n, INT8_OPS)
        export_detector(det_net, out / DETECTOR_FILE, det_cfg["input_width"], det_cfg["input_height"],
                        det_cfg["max_detections"])
        m = {"export.relation.networks": float(len(getattr(net, "members", [net]))),
             "export.relation.params": float(count_parameters(net)),
             "export.relation.size_mb": size_mb(out / RELATION_FILES["static"]),
             "export.relation.int8.size_mb": size_mb(out / RELATION_FILES["int8"]),
             "export.detector.params": float(sum(p.numel() for p in det_net.parameters())),
             "export.detector.size_mb": size_mb(out / DETECTOR_FILE)}
        m.update(relation_latency(net, out, graphs, size, n, lat))
        m.update(detector_latency(det_net, out, images.astype(np.float32), lat))
        m["flip_average"] = float(bool(rel["decode"].get("flip_average", False)))
        if len(getattr(net, "members", [net])) > 1:  # the reference: one network, timed in the same run
            from stages.relation.model import ModelConfig, RelationNet

            one = out / "one_network"
            one.mkdir()
            alone = RelationNet(ModelConfig.from_cfg(OmegaConf.create(rel))).eval()
            export_relation_models(alone, one, size, n, INT8_OPS)
            timed = relation_latency(alone, one, graphs, size, n, lat)
            m["one_network_ms_per_img_b1"] = timed["export.relation.ms_per_img_b1"]
            m["one_network_cpu_ms_per_img_b1"] = timed["export.relation.cpu_ms_per_img_b1"]
    return m


def ratios(m: dict[str, float]) -> str:
    r = {k.removeprefix("export.relation."): v for k, v in m.items()}
    lines = [f"relation model: {r['networks']:.0f} network(s) in one graph, as the default config ships it",
             f"target: onnxruntime >= {TARGET_SPEEDUP}x faster than PyTorch eager"]
    for key, what in (("ms_per_img_b1", "batch 1"), ("ms_per_10img_b10", "batch 10")):
        lines.append(f"{what}: {r[key]:.2f} ms wall ({r['cpu_' + key]:.2f} ms one-thread CPU time) = "
                     f"{r[key] / TARGET[key]:.2f}x the target {TARGET[key]} ms, {r[key] / DSP_LATENCY[key]:.2f}x the "
                     f"paper's DSP; static model padded: {r['static_' + key]:.2f} ms")
    calls = 2 if m.get("flip_average") else 1  # relation.decode.flip_average: the image and its mirror, two calls
    shipped = calls * r["ms_per_img_b1"]
    lines.append(f"as shipped ({calls} call(s) an image, relation.decode.flip_average "
                 f"{'on' if calls == 2 else 'off'}): {shipped:.2f} ms an image at batch 1 = "
                 f"{shipped / TARGET['ms_per_img_b1']:.2f}x the target")
    if "one_network_ms_per_img_b1" in m:
        one = m["one_network_ms_per_img_b1"]
        cpu_one, cpu_shipped = m["one_network_cpu_ms_per_img_b1"], calls * r["cpu_ms_per_img_b1"]
        lines.append(f"one network, same run: {one:.2f} ms a call, {2 * one:.2f} ms with its mirror; the shipped "
                     f"{r['networks']:.0f} networks cost {shipped / (2 * one):.2f}x one network with its mirror "
                     f"({cpu_shipped / (2 * cpu_one):.2f}x in one-thread CPU time, the figure to trust on a loaded host)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from stages.export.stage import latency_table

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--runs", type=int, default=50)
    p.add_argument("--warmup", type=int, default=10)
    args = p.parse_args(argv)
    m = measure(args.threads, args.runs, args.warmup)
    print(f"Latency, median of {args.runs} runs after {args.warmup} warm-up runs, {args.threads} intra-op threads "
          "(onnxruntime and PyTorch eager, same process)\n")
    print(latency_table(m))
    print(ratios(m))


if __name__ == "__main__":
    main()
