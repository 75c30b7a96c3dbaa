"""Plan-time estimates of the stages that train nothing: ``priors`` (mixture fits),
``export`` (ONNX export, parity, latency tables, the operating-point search), ``evaluate`` (every test image through
the bundle and the baselines) and ``bev`` (footprint fits). The engine calls them as ``estimate:`` hooks
(pipeline/estimate.py) for the stages the plan marks MISS.

Their inputs (trained networks, detections) do not exist at plan time, so each estimate counts the calls the stage
makes from the configured image counts and times one call of each kind here, on this host, with the configured
architectures at random weights (a network's speed does not depend on its weights):

- the detector and the relation network exported to ONNX and run by onnxruntime at batch 1 with the export stage's
  threads, as the bundle runs them, and eagerly in PyTorch (the export stage's parity and latency rows);
- PNG decoding of an image of the data's size (every stage reads its images from disk);
- the mixture fits of the priors stage and the silhouette fits of the bev stage, on synthetic inputs.

The work that is neither (matching, counting, records, figures) is counted per image at the rate profiled on a 2-core
Zen 4 host (the ``*_S`` constants below; docs/engine.md gives the estimates against the stages' times), so on a host
whose Python runs slower these read short. The probe costs a few
seconds at plan time (the two ONNX exports most of it), once per process and configuration.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from stages.estimate import (
    MEAN_OBJECTS,
    VEHICLE_SHARE,
    _plain,
    _threads,
    camera_count,
    split_images,
    timed_steps,
)

WHEELS = MEAN_OBJECTS * (1 - VEHICLE_SHARE)   # an image's wheels, on average
VEHICLES = MEAN_OBJECTS * VEHICLE_SHARE


def _images(cfg: DictConfig, split: str) -> int:
    return split_images(cfg, split) or 0


def _test_images(data: DictConfig | None) -> int:
    """frames x cameras x the test share of a data config (``data`` or ``shift.data``); 0 where it names no frames."""
    if data is None:
        return 0
    return split_images(OmegaConf.create({"data": _plain(data)}), "test") or 0


def _in_run(cfg: DictConfig, stage: str) -> bool:
    return stage not in (OmegaConf.select(cfg, "pipeline.skip", default=None) or [])


# -- the unit calls, timed once per process and configuration --------------------------------------------------

_UNITS: dict[str, dict] = {}
RELATION_CALLS_A_STEP = 20


def unit_calls(cfg: DictConfig) -> dict:
    """Seconds of one call of each kind the stages after training make, on this host, at batch 1 with the export
    stage's threads: ``detector`` and ``relation`` in onnxruntime (an image letterboxed to the input; an image's graph
    of MEAN_OBJECTS objects), ``detector_eager`` and ``relation_eager`` in PyTorch (the export stage's parity and
    latency rows, the operating-point search's embedding), ``detector_export`` and ``relation_export`` (one ONNX
    export and its check) and ``decode`` (a PNG of the data's image size). ``relation`` and ``detector`` are timed
    with every output computed, as the stages call them."""
    key = json.dumps([_plain(cfg.detector), _plain(cfg.relation), _plain(OmegaConf.select(cfg, "data.image_size")),
                      _plain(cfg.export.latency), _in_run(cfg, "detector")], sort_keys=True, default=str)
    if key not in _UNITS:
        _UNITS[key] = _time_unit_calls(cfg)
    return _UNITS[key]


def _timed_once(call) -> float:
    started = time.perf_counter()
    call()
    return time.perf_counter() - started


def _time_unit_calls(cfg: DictConfig) -> dict:
    import torch

    from deepword.inference.runtime import DETECTOR_INPUT, RELATION_INPUTS, ort_session
    from deepword.relation_graph import InputConfig
    from stages.detector.model import build_centernet, model_config
    from stages.export.onnx_export import RelationGraph, export_detector, export_relation, relation_example
    from stages.relation.model import ModelConfig, RelationNet

    threads = int(cfg.export.latency.threads)
    det = _plain(cfg.detector)
    in_cfg = InputConfig.from_cfg(cfg.relation)
    units = {"threads": threads}
    with _threads(threads), tempfile.TemporaryDirectory(prefix="deepword-estimate-") as tmp:
        torch.manual_seed(0)
        net = RelationNet(ModelConfig.from_cfg(cfg.relation)).eval()
        path = Path(tmp) / "relation.onnx"
        units["relation_export"] = _timed_once(
            lambda: export_relation(net, path, in_cfg.input_size, in_cfg.max_objects, static=False))
        session = ort_session(path, threads)
        example = relation_example(MEAN_OBJECTS, in_cfg.input_size, batch=1)
        feed = {name: t.numpy() for name, t in zip(RELATION_INPUTS, example, strict=True)}
        # a call takes well under a millisecond: timed RELATION_CALLS_A_STEP at a time, so the median is steady
        units["relation"] = timed_steps(lambda: [session.run(None, feed) for _ in range(RELATION_CALLS_A_STEP)]) \
            / RELATION_CALLS_A_STEP
        graph_net = RelationGraph(net).eval()
        with torch.inference_mode():
            units["relation_eager"] = timed_steps(lambda: graph_net(*example))
        if _in_run(cfg, "detector"):
            det_net = build_centernet(model_config(det)).eval()
            path = Path(tmp) / "detector.onnx"
            width, height = int(det["input_width"]), int(det["input_height"])
            units["detector_export"] = _timed_once(
                lambda: export_detector(det_net, path, width, height, int(det["max_detections"])))
            session = ort_session(path, threads)
            x = np.zeros((1, 3, height, width), np.float32)
            units["detector"] = timed_steps(lambda: session.run(None, {DETECTOR_INPUT: x}))
            with torch.inference_mode():
                units["detector_eager"] = timed_steps(lambda: det_net(torch.from_numpy(x)))
    units["decode"] = decode_seconds(cfg)
    return units


def decode_seconds(cfg: DictConfig) -> float:
    """Seconds to decode one PNG of the data's image size: a rendered-like picture (smooth shading and edges) rather
    than noise, which PNG cannot compress."""
    import cv2

    width, height = (int(v) for v in (_plain(OmegaConf.select(cfg, "data.image_size")) or (640, 480)))
    yy, xx = np.mgrid[0:height, 0:width]
    picture = np.stack([xx * 255 // width, yy * 255 // height, (xx // 40 + yy // 40) % 2 * 200],
                       axis=-1).astype(np.uint8)
    png = cv2.imencode(".png", picture)[1]
    return timed_steps(lambda: cv2.imdecode(png, cv2.IMREAD_COLOR))


# -- priors ---------------------------------------------------------------------------------------------------

# The priors stage's pairs and ratios, counted per train image: 0.70 s for 726 images on the Zen 4 host
RATIOS_PER_IMAGE_S = 0.001


def priors(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the priors stage: every train image's candidate pairs and their ratios, and a mixture fit per
    component count for the true pairs and the non-pairs of both pair types (each on the train split's pairs, at
    most ``priors.max_fit_samples``), the four fits run here on as many synthetic log-ratios."""
    train = split_images(cfg, "train")
    if train is None:
        return None
    started = time.perf_counter()
    import sklearn.mixture  # noqa: F401  (timed: what the stage's first fit pays; nothing when already loaded)

    from deepword.priors import fit_mixture_bic

    seconds = time.perf_counter() - started + train * RATIOS_PER_IMAGE_S
    pc = _plain(cfg.priors)
    limit = int(pc["max_fit_samples"])
    samples = [train * WHEELS, train * WHEELS * (VEHICLES - 1),          # wheel-vehicle pairs, non-pairs
               train * WHEELS / 2, train * WHEELS * (WHEELS - 1.5)]      # wheel-wheel couples, non-couples
    samples = [min(limit, max(2, int(n))) for n in samples]
    rng = np.random.default_rng(0)
    for n in samples:   # log distance ratios spread as the non-pairs' (median 2.5, 90 % within 0.5 .. 4.3)
        started = time.perf_counter()
        fit_mixture_bic(rng.normal(2.5, 1.1, n), tuple(pc["components"]), int(cfg.seed), int(pc["n_init"]),
                        float(pc["reg_covar"]))
        seconds += time.perf_counter() - started
    return {"seconds": seconds,
            "note": f"{train} train images' pairs, 4 mixture fits of {'/'.join(str(n) for n in samples)} samples",
            "hint": f"fewer samples a fit (priors.max_fit_samples, now {limit})"}


def _no_wheel_fit_seconds(cfg: DictConfig) -> float | None:
    """Seconds of one no-wheel footprint fit over the searched sizes (``deepword.footprint.fit_sized`` of
    ``fit_free``): a car 7 m ahead of and 2.5 m beside the configured front camera, fitted to its own silhouette's box
    from a start 1 m off, its axis searched along the viewing direction (no neighbour's axis); None without a camera
    in the data config."""
    from deepword.footprint import FootprintPrior, fit_free, fit_sized, silhouette_boxes
    from deepword.format_3d import Box3D
    from stages.data.camera import nominal_camera

    cameras = _plain(OmegaConf.select(cfg, "data.cameras", default=None)) or {}
    front = next((v for v in cameras.values() if isinstance(v, dict) and "K" in v), None)
    if front is None:
        return None
    size = cameras.get("reference_size") or [640, 480]
    cam = nominal_camera("probe", front, int(size[0]), int(size[1]), size)
    prior = FootprintPrior(width=1.8, length=4.4, wheelbase=2.7, length_slope=1.2, length_offset=1.2,
                           track_inset=0.15, contact_shift=0.1, box_shift=0.5)
    centre, yaw = np.array([[cam.translation[0] + 7.0, 2.5]]), np.array([0.4])
    vbox = silhouette_boxes(cam, centre, yaw, (prior.length, prior.width, prior.height), prior.shape)[0]
    start = Box3D(float(centre[0, 0]) - 0.8, float(centre[0, 1]) + 0.5, prior.length, prior.width, 0.0)
    return timed_steps(lambda: fit_sized(fit_free, cam, vbox, prior, start, None))


# -- export -----------------------------------------------------------------------------------------------------

# What the unit calls leave out, measured on the quick run on a 2-core Zen 4 host (export 61 s, evaluate 45 s, bev 66 s;
# cProfile for the shares): the operating-point search's counting and the fallback rule a val image (its distinct box
# subsets, ~20 an image, scored through the relation heads), and the relation network's eager embedding of each
# image's boxes, in eager relation calls
OP_SEARCH_PER_VAL_IMAGE_S = 0.13
OP_EMBED_CALLS_PER_VAL_IMAGE = 24
# the relation latency table: at batch 1 and 10, onnxruntime at two threads and one, static and dynamic models, in
# calls of the dynamic model at batch 1 (the static model pads each graph to max_objects), and 11 eager calls
LATENCY_RELATION_CALLS, LATENCY_RELATION_EAGER_CALLS = 136, 11
PARITY_PADDING = 1.5   # parity runs batches of 16 graphs padded to the largest: a graph costs this many of its own
FACING_PER_TEST_IMAGE_S = 0.02   # the facing network's crops of a test image, exported and checked on them
REGISTRY_S = 3.5       # logging and registering the two models in MLflow
EXPORT_OTHER_S = 5.0   # loading the networks, fitting the bundle's IoU rule on train, INT8 quantisation, the bundle


def export(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the export stage: the ONNX exports, the relation parity of its three variants and the INT8
    accuracy change on every test image, the detector's parity and latency table, the relation latency table, the
    detector's operating point searched on val (the detector on each val image, the relation heads on its box
    subsets), the facing network's check and the model registry, each as the calls it makes x the unit calls timed
    here."""
    test, val = _images(cfg, "test"), _images(cfg, "val")
    if not test:
        return None
    u, ex = unit_calls(cfg), cfg.export
    calls = int(ex.latency.runs) + int(ex.latency.warmup)
    parity_images = min(test, int(ex.parity.images)) if ex.parity.images is not None else test
    rel_call = u["relation"] + u["relation_eager"]
    parts = {
        "exports": 2 * u["relation_export"] + 2 * u.get("detector_export", 0.0) + EXPORT_OTHER_S,
        "parity": parity_images * (u["decode"] + 4 * PARITY_PADDING * rel_call),
        "latency": calls * (LATENCY_RELATION_CALLS * u["relation"] + LATENCY_RELATION_EAGER_CALLS * u["relation_eager"]),
        "facing": test * FACING_PER_TEST_IMAGE_S if _in_run(cfg, "facing") else 0.0,
        "registry": REGISTRY_S if bool(ex.register) else 0.0,
    }
    if _in_run(cfg, "detector"):
        det_parity = min(test, int(ex.parity.detector_images))
        parts["parity"] += det_parity * (u["decode"] + u["detector"] + u["detector_eager"])
        parts["latency"] += calls * (11 * u["detector"] + u["detector_eager"])
        parts["operating point"] = val * (u["decode"] + u["detector"] + OP_EMBED_CALLS_PER_VAL_IMAGE
                                          * u["relation_eager"] + OP_SEARCH_PER_VAL_IMAGE_S)
    networks = (f"detector {1000 * u['detector']:.1f} ms, " if "detector" in u else "") + \
        f"relation {1000 * u['relation']:.2f} ms in onnxruntime"   # a run without the detector times no detector
    return {"seconds": sum(parts.values()),
            "note": ", ".join(f"{k} {v:.0f} s" for k, v in parts.items() if v) + f" ({test} test, {val} val images; "
                    f"{networks})",
            "hint": f"fewer latency runs (export.latency.runs, now {int(ex.latency.runs)}) or parity images "
                    "(export.parity.images)"}


# -- evaluate ---------------------------------------------------------------------------------------------------

# Per test image, what is not a network call: matching and scoring the methods' predictions (COCO AP and its error
# breakdown, pair errors), the hand-written rules' predictions, reading and writing records, the gallery
EVAL_OTHER_PER_IMAGE_S = 0.041
EVAL_FIT_PER_TRAIN_IMAGE_S = 0.0083   # the baselines' parameter search, per train image it is fitted on
GRAPH_S = 0.001                       # building an image's relation graph (its crops) from the decoded image
IMAGE_READS = 3                       # each test image is decoded about three times (detector, relations, AP)


def evaluate(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the evaluate stage: the baselines fitted on ``eval.fit_images`` train images, then every in-domain
    and held-out test image through the exported detector (detected boxes) and the relation model for each
    DeepWORD row and box source (twice with ``relation.decode.flip_average``: the image and its mirror), decoded
    about IMAGE_READS times, and scored."""
    if split_images(cfg, "test") is None:   # a dataset read from disk: its images are counted once the data stage ran
        return None
    test = _images(cfg, "test") + (_test_images(OmegaConf.select(cfg, "shift.data")) if _in_run(cfg, "shift_data")
                                   else 0)
    if not test:
        return None
    u, ev = unit_calls(cfg), cfg.eval
    sources = [s for s in ev.box_sources if s != "detected" or _in_run(cfg, "detector")]
    variants = sum(1 for m in ev.methods if m in ("deepword", "deepword_int8"))
    views = 2 if bool(OmegaConf.select(cfg, "relation.decode.flip_average", default=False)) else 1
    per_image = {"detector": u["detector"] if "detected" in sources else 0.0,
                 "relation": len(sources) * variants * (views * u["relation"] + GRAPH_S),
                 "decoding": IMAGE_READS * u["decode"], "scoring": EVAL_OTHER_PER_IMAGE_S}
    fit = min(int(ev.fit_images), _images(cfg, "train")) * EVAL_FIT_PER_TRAIN_IMAGE_S
    seconds = fit + test * sum(per_image.values())
    return {"seconds": seconds,
            "note": f"{test} test images x ({', '.join(f'{k} {1000 * v:.0f} ms' for k, v in per_image.items())}) + "
                    f"fitting the baselines {fit:.0f} s",
            "hint": f"fewer rows (eval.methods) or baseline fit images (eval.fit_images, now {int(ev.fit_images)})"}


# -- bev --------------------------------------------------------------------------------------------------------

# Footprint fits per test image and box source on the quick run, counted (the box_bottom row fits every vehicle box
# without wheels; the relation methods' fits of one vehicle are shared): 2.4 no-wheel fits and 2.6 one-wheel ones,
# a one-wheel fit costing 0.39 of a no-wheel one on average (most take a neighbour's axis): in no-wheel fits
FITS_PER_IMAGE = 2.4 + 2.6 * 0.39
PROCESS_START_S = 2.5          # a spawned fitting process before it fits (bev.workers)
FACING_PER_IMAGE_S = 0.010     # the facing network on an image's vehicle boxes, per box source (onnxruntime)
SCORING_PER_FRAME_S = 0.0085   # matching and nuScenes-style scores of a frame's fused footprints, per (boxes, method)
FIGURE_S = 0.04                # a top-view figure
PRIOR_FIT_PER_IMAGE_S = 0.002  # the footprint prior, per train image it is fitted on (bev.fit_images)


def bev(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the bev stage: the footprint fits of every in-domain and held-out test image for each box source,
    shared among ``bev.workers`` processes (one a frame's fits, at most one per 8 frames), timed here as no-wheel
    fits; the facing network on each vehicle box; scoring each frame for every (box source, method) and the
    top-view figures, after fitting the footprint prior on train."""
    from deepword.frame_processes import frame_processes

    if split_images(cfg, "test") is None:
        return None
    fit_s = _no_wheel_fit_seconds(cfg)
    n_cameras = camera_count(cfg)
    domains = [_images(cfg, "test")]
    if _in_run(cfg, "shift_data"):
        domains.append(_test_images(OmegaConf.select(cfg, "shift.data")))
    images = sum(domains)
    if fit_s is None or not images:
        return None
    bc, decode_s = cfg.bev, decode_seconds(cfg)   # no network call: the unit calls' exports are not needed
    sources = [s for s in bc.box_sources if s != "detected" or _in_run(cfg, "detector")]
    workers = int(bc.workers or os.cpu_count() or 1)
    fits, most = 0.0, 1
    for n in domains:   # each domain's frames shared among the processes separately
        frames = math.ceil(n / max(1, n_cameras))
        processes = frame_processes(workers, frames)
        most = max(most, processes)
        fits += n * len(sources) * FITS_PER_IMAGE * fit_s / processes + (PROCESS_START_S if processes > 1 else 0.0)
    jobs = len(sources) * (len(bc.methods) + 1)   # + box_bottom
    rest = images * len(sources) * (decode_s + FACING_PER_IMAGE_S) \
        + images / max(1, n_cameras) * jobs * SCORING_PER_FRAME_S + len(domains) * int(bc.figures) * FIGURE_S \
        + min(int(bc.fit_images), _images(cfg, "train")) * PRIOR_FIT_PER_IMAGE_S
    return {"seconds": fits + rest,
            "note": f"{images} test images x {len(sources)} box sources x ~{FITS_PER_IMAGE:.1f} fits of "
                    f"{1000 * fit_s:.0f} ms in {most} process{'es' if most > 1 else ''} ({fits:.0f} s), facing votes and scoring "
                    f"({rest:.0f} s)",
            "hint": "fewer relation methods (bev.methods) or box sources (bev.box_sources), more cores"}
