"""Training throughput: images/s of the detector's optimisation step (forward, loss, backward, AdamW) in fp32
against channels_last, bf16 autocast, and both, in the same process on the same batches; the AdamW and
weight-average updates after each step, torch's per-tensor way against the stage's fused and multi-tensor one;
the training loader's time per item and its share of an epoch beside the fastest step; the relation network's
step with its crop backbone in fp32, fp32 channels_last and bf16 + channels_last, and the facing network's in the
same layouts and precisions (stages/training/memory_format.py says which the stages take); and how close each step
comes to the host's limit: the step's floating-point operations (forward and backward, counted by
``torch.utils.flop_counter``) per second of its median time, against the rate of a large matrix product timed in
the same run in the same precision (the host's practical peak).
A step far under the peak wants faster code (kernels, layouts, less overhead between them); one near it wants
less work (a smaller network, fewer or smaller images).

    python -m benchmarks.bench_detector_training [--threads 2] [--steps 6] [--batch 8]

The network is the default config's CenterNet (conf/detector, tiny backbone), freshly initialised; the
batch is the quick profile's training crop (320x256) with random images and real targets of the configured
box regression (``detector.regression``).
Variants are interleaved step by step (fp32, fp32 channels_last, bf16, both, fp32, ...) so that the load other
processes put on a shared machine falls on all of them alike; the medians' ratios against fp32 are the
figures to trust, the absolute rates depend on the load. bf16 is only timed where the CPU runs it natively
(``stages.training.precision.cpu_has_native_bf16``): elsewhere emulated bf16 is slower and the stages train in fp32.
The ratio is printed, never asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import statistics
import time

import numpy as np

from benchmarks.bench_latency import CONF, default_configs


def make_batch(det: dict, batch: int, width: int, height: int, seed: int = 0) -> dict:
    import torch

    from stages.detector.model import CLASS_NAMES, DOWN_RATIO
    from stages.detector.targets import centernet_targets, ttfnet_box_targets

    rng = np.random.default_rng(seed)
    items = []
    for _ in range(batch):
        x1 = rng.uniform(0, width - 40, 12)
        y1 = rng.uniform(0, height - 30, 12)
        boxes = np.column_stack([x1, y1, x1 + rng.uniform(8, 40, 12), y1 + rng.uniform(8, 30, 12)])
        item = centernet_targets(boxes / DOWN_RATIO, rng.integers(0, 2, 12), len(CLASS_NAMES),
                                 width // DOWN_RATIO, height // DOWN_RATIO, 12, det["min_overlap"])
        if det["regression"] == "ttfnet":
            item |= ttfnet_box_targets(boxes, width // DOWN_RATIO, height // DOWN_RATIO, DOWN_RATIO)
        items.append(item)
    out = {k: torch.from_numpy(np.stack([it[k] for it in items])) for k in items[0]}
    out["image"] = torch.from_numpy(rng.standard_normal((batch, 3, height, width)).astype(np.float32))
    return out


def interleaved_times(step, names: list[str], steps: int) -> dict[str, list[float]]:
    """Seconds of ``step(name)`` per name: one warm-up each (oneDNN primitive creation), then ``steps`` rounds
    that run every name once, so a shared machine's load falls on all of them alike."""
    for name in names:
        step(name)
    times: dict[str, list[float]] = {name: [] for name in names}
    for _ in range(steps):
        for name in names:
            times[name].append(step(name))
    return times


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=6, help="timed steps per variant (after one warm-up)")
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args(argv)

    import torch

    from stages.detector.losses import detector_loss
    from stages.detector.model import DOWN_RATIO, build_centernet, model_config
    from stages.training.precision import cpu_has_native_bf16

    torch.set_num_threads(args.threads)
    _, det = default_configs()
    width, height = 320, 256
    batch = make_batch(det, args.batch, width, height)
    native_bf16 = cpu_has_native_bf16()
    variants = {"fp32": (False, False), "fp32 channels_last": (False, True)}
    if native_bf16:
        variants |= {"bf16": (True, False), "bf16 + channels_last": (True, True)}

    state = {}
    for name, (_, channels_last) in variants.items():
        torch.manual_seed(0)
        net = build_centernet(model_config(det)).train()
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        net = net.to(memory_format=fmt)
        state[name] = (net, torch.optim.AdamW(net.parameters(), lr=1e-4), batch["image"].contiguous(memory_format=fmt))

    def step(name: str) -> float:
        bf16, _ = variants[name]
        net, opt, images = state[name]
        start = time.perf_counter()
        autocast = torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()
        with autocast:
            loss, _ = detector_loss(net(images), batch, det["regression"], DOWN_RATIO, det["loss"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        return time.perf_counter() - start

    times = interleaved_times(step, list(variants), args.steps)
    peaks = matmul_peaks(native_bf16)
    step_flops = training_flops(lambda: detector_loss(state["fp32"][0](state["fp32"][2]), batch,
                                                      det["regression"], DOWN_RATIO, det["loss"])[0])

    print(f"CPU native bf16: {native_bf16}; threads {args.threads}; batch {args.batch} at {width}x{height}; "
          f"median of {args.steps} interleaved steps")
    print_ratios(times, args.batch, "images/s")
    utilisation("detector", step_flops, {name: statistics.median(ts) for name, ts in times.items()}, peaks)
    fastest = min(statistics.median(ts) for ts in times.values()) / args.batch
    update_costs(det, fastest * args.batch, max(20, 4 * args.steps))
    loader_share(det, fastest, args.steps)
    relation_step_ratio(args.steps, peaks, native_bf16)
    facing_step_ratio(args.steps, peaks, native_bf16)
    if not native_bf16:
        print("\nbf16 not timed: this CPU has no native bf16 (avx512_bf16 / amx_bf16); the stages train in fp32")


def matmul_peaks(native_bf16: bool, size: int = 2048, rounds: int = 5) -> dict[str, float]:
    """FLOP/s of a size x size x size matrix product, fp32 and (where the CPU has it natively) bf16: the best of
    ``rounds`` after a warm-up, the practical peak a training step is compared with."""
    import torch

    peaks = {}
    for dtype_name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        if dtype_name == "bf16" and not native_bf16:
            continue
        a = torch.randn(size, size, dtype=dtype)
        b = torch.randn(size, size, dtype=dtype)
        a @ b
        best = min(_timed(lambda a=a, b=b: a @ b) for _ in range(rounds))
        peaks[dtype_name] = 2 * size ** 3 / best
    rates = ", ".join(f"{name} {rate / 1e9:.0f} GFLOP/s" for name, rate in peaks.items())
    print(f"host peak (matrix product {size}^3, best of {rounds}): {rates}")
    return peaks


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def training_flops(loss_fn) -> int:
    """Floating-point operations of one forward and backward pass (``torch.utils.flop_counter``: matrix products
    and convolutions, which are nearly all of a convolutional network's; elementwise work is not counted)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        loss_fn().backward()
    return counter.get_total_flops()


def utilisation(network: str, flops: int, median_seconds: dict[str, float], peaks: dict[str, float]) -> None:
    """Achieved FLOP/s of each variant's median step against the peak of its precision."""
    print(f"\n{network} step: {flops / 1e9:.2f} GFLOP (forward + backward); achieved against the host's peak")
    print(f"{'variant':<22} {'GFLOP/s':>8} {'of peak':>8}")
    for name, seconds in median_seconds.items():
        precision = "bf16" if name.startswith("bf16") else "fp32"
        rate = flops / seconds
        print(f"{name:<22} {rate / 1e9:8.1f} {100 * rate / peaks[precision]:7.1f}%  ({precision} peak)")


def update_costs(det: dict, step_seconds: float, rounds: int) -> None:
    """What follows every training step of the detector, on its parameters: the AdamW update and the weight
    average's (``detector.ema_decay``), each the way torch and Lightning do it by default (a few ops per tensor,
    one tensor after another) against the way the detector stage does it (fused AdamW, one multi-tensor lerp for
    the average), interleaved; with their share of the fastest step above, which does not include them."""
    import torch
    from torch.optim.swa_utils import AveragedModel, get_ema_avg_fn, get_ema_multi_avg_fn

    from stages.detector.model import build_centernet, model_config

    torch.manual_seed(0)
    net = build_centernet(model_config(det))
    for p in net.parameters():
        p.grad = torch.randn_like(p)
    decay = float(det["ema_decay"]) or 0.998
    # (kind, way) -> the update: AdamW's step, or the average's update from the network's weights
    calls = {("AdamW", "per tensor"): torch.optim.AdamW(net.parameters(), lr=1e-4, foreach=False).step,
             ("AdamW", "stage"): torch.optim.AdamW(net.parameters(), lr=1e-4, fused=True).step}
    for way, averaging in (("per tensor", {"avg_fn": get_ema_avg_fn(decay)}),
                           ("stage", {"multi_avg_fn": get_ema_multi_avg_fn(decay)})):
        averaged = AveragedModel(net, use_buffers=True, **averaging)
        averaged.update_parameters(net)  # the first update copies
        calls["weight average", way] = functools.partial(averaged.update_parameters, net)

    def run(name) -> float:
        start = time.perf_counter()
        calls[name]()
        return time.perf_counter() - start

    times = interleaved_times(run, list(calls), rounds)
    tensors = len(list(net.parameters()))
    print(f"\nupdate after each step ({tensors} parameter tensors), median of {rounds} interleaved updates")
    print(f"{'update':<30} {'per tensor ms':>13} {'stage ms':>9} {'ratio':>6}  share of a step, per tensor -> stage")
    for kind in ("AdamW", "weight average"):
        slow, fast = statistics.median(times[kind, "per tensor"]), statistics.median(times[kind, "stage"])
        label = "fused" if kind == "AdamW" else "multi-tensor"
        share_slow, share_fast = (100 * t / (step_seconds + t) for t in (slow, fast))
        print(f"{kind + ' (' + label + ')':<30} {1000 * slow:13.2f} {1000 * fast:9.2f} {slow / fast:5.1f}x  "
              f"{share_slow:.0f}% -> {share_fast:.0f}%")


def synthetic_scene(width: int, height: int, rng: np.random.Generator, objects: int = 12):
    """A letterboxed-like training image (smooth background, filled boxes: noise would make the JPEG effect
    unrealistically slow), its record in input pixels and its boxes' facing vectors (none known), as
    ``CenterNetDataset.letterboxed`` caches them."""
    import cv2

    from deepword.word_format import Record

    ramp = np.linspace(60, 200, width, dtype=np.float32)
    image = np.repeat(np.stack([ramp, ramp[::-1], np.full_like(ramp, 128)], -1)[None], height, 0).astype(np.uint8)
    x1, y1 = rng.uniform(0, width - 60, objects), rng.uniform(0, height - 40, objects)
    xyxy = np.column_stack([x1, y1, x1 + rng.uniform(8, 60, objects), y1 + rng.uniform(8, 40, objects)])
    for box in xyxy.astype(int):
        cv2.rectangle(image, tuple(box[:2]), tuple(box[2:]), tuple(int(c) for c in rng.integers(0, 255, 3)), -1)
    boxes = np.column_stack([xyxy, np.ones(objects), rng.integers(0, 2, objects), np.arange(objects)])
    record = Record(image="synthetic.png", frame_id=0, camera="front", width=width, height=height, boxes=boxes,
                    relations=[], wheel_pairs=[])
    return image, record, np.full((objects, 2), np.nan, dtype=np.float32)  # no 3D truth: no facing vectors


def loader_share(det: dict, step_seconds_per_image: float, rounds: int, items: int = 40) -> None:
    """The detector's training loader per item (``CenterNetDataset.__getitem__`` with the default augmentation, on
    cached letterboxed images, as from the second epoch on) at the quick profile's input (480x352, 320x256 crops)
    and the full profile's (whole 640x480 images), against the fastest training step above per image: the share of
    an epoch the loader takes when it runs in the training process (no loader workers, a CPU's default). The step
    was timed on 320x256 crops; for whole 640x480 images it is scaled by the pixel count (a convolutional network's
    cost grows with it)."""
    import torch

    from stages.detector.dataset import CenterNetDataset

    print(f"\ntraining loader, median of {rounds} rounds of {items} items (default augmentation)")
    print(f"{'input':<30} {'ms/item':>8} {'share of an in-process epoch':>29}")
    for name, (width, height, crop) in {"quick: 480x352, 320x256 crops": (480, 352, [320, 256]),
                                        "full: whole 640x480": (640, 480, None)}.items():
        rng = np.random.default_rng(0)
        augment = {**det["augment"], "crop": crop}
        dataset = CenterNetDataset(".", [], width, height, 12, augment=augment, regression=det["regression"])
        scenes = [synthetic_scene(width, height, rng) for _ in range(items)]
        dataset.records = [record for _, record, _ in scenes]
        dataset._cache = dict(enumerate(scenes))
        torch.manual_seed(0)
        times = []
        for _ in range(rounds):
            start = time.perf_counter()
            for i in range(items):
                dataset[i]
            times.append((time.perf_counter() - start) / items)
        loader = statistics.median(times)
        trained = crop or (width, height)
        step = step_seconds_per_image * trained[0] * trained[1] / (320 * 256)
        share = loader / (loader + step)
        print(f"{name:<30} {1000 * loader:8.1f} {100 * share:28.0f}%")


def relation_step_ratio(steps: int, peaks: dict[str, float], native_bf16: bool, images: int = 16) -> None:
    """The relation stage's training step (default config, 16 images of the quick profile's object counts) with the
    crop backbone in fp32 NCHW, fp32 channels_last and (where the CPU has it natively) bf16 channels_last,
    interleaved; prints graphs/s, the ratios and the share of the peak."""
    import torch
    from omegaconf import OmegaConf

    from benchmarks.bench_latency import TEST_OBJECT_COUNTS, random_graphs
    from deepword.relation_graph import InputConfig
    from stages.relation.lightning import RelationModule, collate_graphs
    from stages.relation.model import ModelConfig

    rel, _ = default_configs()
    cfg = OmegaConf.create(rel)
    in_cfg, model_cfg = InputConfig.from_cfg(cfg), ModelConfig.from_cfg(cfg)
    graphs = random_graphs(TEST_OBJECT_COUNTS[:images], in_cfg.input_size)
    items = []
    for g in graphs:
        n = len(g.classes)
        items.append({"crops": torch.from_numpy(g.crops), "coords": torch.from_numpy(g.coords),
                      "classes": torch.from_numpy(g.classes).long(), "valid": torch.from_numpy(g.valid),
                      "adj": torch.from_numpy(g.adj), "cand": torch.from_numpy(g.cand),
                      "owner": torch.zeros((n, n), dtype=torch.uint8), "couple": torch.zeros((n, n), dtype=torch.uint8),
                      "role": torch.full((n,), -1, dtype=torch.long)})
    batch = collate_graphs(items)
    variants = {"fp32": (False, False), "fp32 channels_last": (False, True)}
    if native_bf16:
        variants["bf16 + channels_last"] = (True, True)
    modules = {}
    for name, (bf16, channels_last) in variants.items():
        torch.manual_seed(0)
        module = RelationModule(model=dict(model_cfg.__dict__), loss=rel["loss"], decode=rel["decode"],
                                optim={"lr": 1e-3, "weight_decay": 0.0}, backbone_bf16=bf16,
                                backbone_channels_last=channels_last).train()
        modules[name] = (module, torch.optim.AdamW(module.parameters(), lr=1e-3))

    def step(name: str) -> float:
        module, opt = modules[name]
        start = time.perf_counter()
        loss = module._loss(module(batch), batch)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        return time.perf_counter() - start

    times = interleaved_times(step, list(modules), steps)
    print(f"\nrelation network ({model_cfg.backbone['_target_'].rsplit('.', 1)[-1]}, {in_cfg.input_size}x"
          f"{in_cfg.input_size} crops), {images} images of {sum(len(g.classes) for g in graphs)} objects per step; "
          "the backbone's layout and precision")
    print_ratios(times, images, "images/s")
    module = modules["fp32"][0]
    flops = training_flops(lambda: module._loss(module(batch), batch)["loss"])
    utilisation("relation", flops, {n: statistics.median(ts) for n, ts in times.items()}, peaks)


def facing_step_ratio(steps: int, peaks: dict[str, float], native_bf16: bool) -> None:
    """The facing network's training step (default config: a batch of 64 crops) in fp32 NCHW, fp32 channels_last and,
    where the CPU has it natively, bf16 in both layouts, interleaved; ratios and the share of the peak."""
    import torch
    from omegaconf import OmegaConf

    from stages.facing.model import FacingNet, facing_loss

    fc = OmegaConf.load(CONF / "facing" / "default.yaml")
    batch, size = int(fc.train.batch_size), int(fc.input_size)
    variants = {"fp32": (False, False), "fp32 channels_last": (False, True)}
    if native_bf16:
        variants |= {"bf16": (True, False), "bf16 + channels_last": (True, True)}
    generator = torch.Generator().manual_seed(0)
    crops = torch.randint(0, 256, (batch, 3, size, size), dtype=torch.uint8, generator=generator)
    targets = torch.nn.functional.normalize(torch.randn(batch, 2, generator=generator), dim=1)
    state = {}
    for name, (_, channels_last) in variants.items():
        torch.manual_seed(0)
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        net = FacingNet(tuple(fc.widths), int(fc.hidden), tuple(fc.convs)).to(memory_format=fmt).train()
        state[name] = (net, torch.optim.AdamW(net.parameters(), lr=1e-3), crops.contiguous(memory_format=fmt))

    def step(name: str) -> float:
        net, opt, x = state[name]
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=variants[name][0]):
            loss = facing_loss(net(x).float(), targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
        return time.perf_counter() - start

    times = interleaved_times(step, list(variants), steps)
    print(f"\nfacing network ({size}x{size} crops, widths {list(fc.widths)}), batch {batch}")
    print_ratios(times, batch, "crops/s")
    net, _, x = state["fp32"]
    flops = training_flops(lambda: facing_loss(net(x), targets))
    utilisation("facing", flops, {n: statistics.median(ts) for n, ts in times.items()}, peaks)


def print_ratios(times: dict[str, list[float]], items: int, unit: str) -> None:
    """Each variant's median step, its rate and its ratio against the first (the fp32 NCHW reference)."""
    reference = statistics.median(next(iter(times.values())))
    print(f"{'variant':<22} {'ms/step':>8} {unit:>9} {'vs fp32':>8}")
    for name, ts in times.items():
        median = statistics.median(ts)
        print(f"{name:<22} {1000 * median:8.0f} {items / median:9.1f} {reference / median:7.2f}x")


if __name__ == "__main__":
    main()
