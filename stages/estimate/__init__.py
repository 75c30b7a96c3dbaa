"""Plan-time estimates of the stages' time on this host (the engine's ``estimate`` hook, pipeline/estimate.py): the
training stages by probes of their steps, the generator's stages (``data``, ``shift_data``) by rendering its first
rig's frames (``data``: a rig's first frame builds its per-pixel tables, each frame is rendered and PNG-written as the
stage does; the frames are shared among the stage's processes). The stages that train nothing (priors, export,
evaluate, bev) are estimated in ``stages.estimate.after_training``.

Each probe builds the configured network, times a few real optimisation steps (forward, loss, backward, AdamW) at the
configured batch size, precision (``trainer.precision``, resolved as the stage resolves it: bf16 where the host runs
it natively) and threads, on synthetic tensors of the configured input size (the dataset need not exist yet), and
multiplies the median step by the steps the configured epochs imply, plus a forward pass per validation batch on the
epochs that validate. The stage's own data loading (decoding and augmenting images, the relation crops) is not in
the probe. Images per epoch are not known before the data stage: the probes take the configured frames x cameras x
split share (``data.frames``, ``data.cameras``, ``data.split``), an upper bound, since the generator drops images
without an owner relation (86 % of the quick profile's train images were kept). Where the data config names no
frames (``data=word``) there is no estimate.

No stage module imports this package, so it is in no stage's code version: a change here re-runs nothing. It is a
package of its own, not a module of stages.training, because it imports the detector and relation stages, which
import stages.training.
"""

from __future__ import annotations

import contextlib
import json
import math
import statistics
import time

import numpy as np
from omegaconf import DictConfig, OmegaConf

PROBE_SECONDS = 1.5   # stop timing steps once this much was spent (after at least MIN_STEPS)
MIN_STEPS, MAX_STEPS = 2, 8
# Mean objects (vehicles and wheels) an image of the generator holds: 13.3 over the first 50 quick-profile test
# images (seed 42). The relation probe's images hold 2 .. 2*13-2 objects, 13 on average.
MEAN_OBJECTS = 13
# The epochs a relation network trains up to its best val wheel_acc on the quick data (its best came in the 5th to 8th):
# with early stopping the probe counts these plus the patience
RELATION_BEST_EPOCH = 6


def _plain(node):
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def camera_count(cfg: DictConfig) -> int:
    """The cameras of the data config's rig (``data.cameras``' entries with intrinsics)."""
    cameras = _plain(OmegaConf.select(cfg, "data.cameras", default=None)) or {}
    return sum(1 for v in cameras.values() if isinstance(v, dict) and "K" in v)


def split_images(cfg: DictConfig, split: str) -> int | None:
    """frames x cameras x the split's share, from the data config; None where it names no frames."""
    frames = OmegaConf.select(cfg, "data.frames", default=None)
    share = OmegaConf.select(cfg, f"data.split.{split}", default=None)
    n_cameras = camera_count(cfg)
    if frames is None or share is None or n_cameras == 0:
        return None
    return int(round(int(frames) * float(share))) * n_cameras


def limited_batches(n_images: int, batch_size: int, limit, drop_last: bool = False) -> int:
    """Batches of an epoch under Lightning's ``limit_*_batches`` (a share when a float, a count when an int)."""
    batches = n_images // batch_size if drop_last and n_images > batch_size else math.ceil(n_images / batch_size)
    if limit is None:
        return batches
    if isinstance(limit, float) and limit <= 1.0:
        return max(1, int(batches * limit)) if batches else 0
    return min(batches, int(limit))


@contextlib.contextmanager
def _threads(n: int):
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def timed_steps(step, sync=lambda: None) -> float:
    """Median seconds of ``step()``: one warm-up (oneDNN creates its primitives), then MIN_STEPS..MAX_STEPS timed,
    stopping once PROBE_SECONDS were spent."""
    step()
    sync()
    times, spent = [], 0.0
    while len(times) < MAX_STEPS and (len(times) < MIN_STEPS or spent < PROBE_SECONDS):
        start = time.perf_counter()
        step()
        sync()
        times.append(time.perf_counter() - start)
        spent += times[-1]
    return statistics.median(times)


def _device(accelerator: str):
    import torch

    from stages.training.precision import trains_on_gpu

    if trains_on_gpu(accelerator):
        return torch.device("cuda"), torch.cuda.synchronize
    return torch.device("cpu"), (lambda: None)


def _replicas(trainer: dict) -> int:
    devices = trainer.get("devices", 1)
    per_node = devices if isinstance(devices, int) and devices > 0 else 1
    return per_node * int(trainer.get("num_nodes", 1) or 1)


def _precision_name(precision: str, channels_last: bool = False) -> str:
    """``bf16`` / ``fp32`` (or Lightning's name), with `` NHWC`` where the network trains channels_last."""
    from stages.training.precision import BF16

    name = "bf16" if precision == BF16 else "fp32" if precision in ("32-true", "32") else precision
    return name + (" NHWC" if channels_last else "")


# -- detector ------------------------------------------------------------------------------------------------


AUTO = "auto"  # detector.epochs: auto sizes the epochs to the host (detector_epochs)


_EPOCH_PROBES: dict[str, dict | None] = {}   # detector_epoch's answers in this process, by what decides them


def detector_epoch(cfg: DictConfig) -> dict | None:
    """One detector epoch on this host: {"epoch_s": training seconds, "validation_s": one validation pass, "how": how
    it was reached}; None where the data config names no frames. Probed once per process and configuration: the
    sizing hook and the estimate hook of one plan read the same probe (their epochs aside, their configs agree)."""
    det = {k: v for k, v in _plain(cfg.detector).items() if k not in ("epochs", "sizing")}
    data = {k: _plain(OmegaConf.select(cfg, f"data.{k}", default=None)) for k in ("frames", "cameras", "split",
                                                                                   "image_size")}
    key = json.dumps([det, _plain(cfg.trainer), data], sort_keys=True, default=str)
    if key not in _EPOCH_PROBES:
        _EPOCH_PROBES[key] = _probe_detector_epoch(cfg)
    return _EPOCH_PROBES[key]


def _probe_detector_epoch(cfg: DictConfig) -> dict | None:
    import torch

    from stages.detector.losses import detector_loss
    from stages.detector.model import DOWN_RATIO, build_centernet, model_config
    from stages.training.loader_workers import loader_workers, usable_cores
    from stages.training.memory_format import use_channels_last
    from stages.training.precision import BF16, resolve_precision

    train_images, val_images = split_images(cfg, "train"), split_images(cfg, "val")
    if train_images is None:
        return None
    det = _plain(cfg.detector)
    trainer = _plain(cfg.trainer)
    batch = int(det["batch_size"])
    precision = resolve_precision(trainer.get("precision", "32-true"), trainer.get("accelerator", "auto"))
    bf16 = precision == BF16
    device, sync = _device(trainer.get("accelerator", "auto"))
    crop = det["augment"].get("crop")
    width, height = (int(crop[0]), int(crop[1])) if crop else (int(det["input_width"]), int(det["input_height"]))
    threads = int(trainer.get("threads") or usable_cores())
    with _threads(threads):
        torch.manual_seed(0)
        mcfg = model_config(det)
        net = build_centernet(mcfg)
        channels_last = use_channels_last(bool(det["channels_last"]), net, bf16, device.type != "cpu", "the detector")
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        net = net.to(device).to(memory_format=fmt).train()
        opt = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=True)
        targets = _detector_targets(det, batch, width, height, device)
        images = torch.randn(batch, 3, height, width, device=device).contiguous(memory_format=fmt)
        autocast = (lambda: torch.autocast(device.type, dtype=torch.bfloat16)) if bf16 else contextlib.nullcontext

        def step():
            with autocast():
                loss, _ = detector_loss(net(images), targets, mcfg["regression"], DOWN_RATIO, det["loss"])
            opt.zero_grad()
            loss.backward()
            opt.step()

        step_s = timed_steps(step, sync)
        net.eval()
        val_input = torch.randn(batch, 3, int(det["input_height"]), int(det["input_width"]),
                                device=device).contiguous(memory_format=fmt)

        def forward():
            with torch.no_grad(), autocast():
                net(val_input)

        forward_s = timed_steps(forward, sync)
        item_s = _loader_item_seconds(cfg, det)
    workers = loader_workers(det.get("num_workers"), trainer.get("accelerator", "auto"))
    # the training process prepares each batch itself without loader workers; with them it waits only when they
    # fall behind the step
    batch_load_s = batch * item_s
    train_step_s = step_s + batch_load_s if workers == 0 else max(step_s, batch_load_s / workers)
    replicas = _replicas(trainer)
    steps = limited_batches(math.ceil(train_images / replicas), batch, det.get("limit_train_batches"), drop_last=True)
    val_batches = limited_batches(math.ceil((val_images or 0) / replicas), batch, det.get("limit_val_batches"))
    epoch_s = steps * train_step_s
    validation_s = val_batches * forward_s
    how = (f"{steps} steps x {1000 * train_step_s:.0f} ms ({1000 * step_s:.0f} ms "
           f"{_precision_name(precision, channels_last)} step, batch {batch} at {width}x{height}, {threads} threads"
           f"{', ' + device.type if device.type != 'cpu' else ''}; "
           f"{1000 * batch_load_s:.0f} ms loading, {workers} loader workers)")
    return {"epoch_s": epoch_s, "validation_s": validation_s, "how": how}


def detector(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the detector's training: epochs x (train steps x the probed step and batch loading), plus its
    validation passes."""
    probe = detector_epoch(cfg)
    if probe is None:
        return None
    det = _plain(cfg.detector)
    epochs = int(det["epochs"])
    val_epochs = epochs // max(1, int(det.get("val_every_n_epochs", 1)))
    epoch_s = probe["epoch_s"]
    seconds = epochs * epoch_s + val_epochs * probe["validation_s"]
    return {"seconds": seconds,
            "note": f"{epochs} epochs x {probe['how']} + {val_epochs} validations; ~{epoch_s:.0f} s an epoch",
            "hint": f"~{epoch_s:.0f} s an epoch: fewer epochs (detector.epochs=N, now {epochs}), a smaller profile "
                    "(profile=smoke), or a GPU (trainer=gpu)"}


def detector_epochs(cfg: DictConfig, context=None) -> dict | None:
    """The detector's ``size`` hook (pipeline.sizing): with ``detector.epochs: auto``, the most epochs whose estimated
    training (``detector_epoch``: steps, batch loading and the validations) fits ``detector.sizing.minutes`` on this
    host, within ``detector.sizing.min_epochs`` .. ``max_epochs``; ``max_epochs`` where the data config names no image
    count (data=word, a composed dataset). Any other value of ``detector.epochs`` is left as given (None)."""
    det = _plain(cfg.detector)
    if det.get("epochs") != AUTO:
        return None
    sizing = det.get("sizing") or {}
    missing = [k for k in ("minutes", "min_epochs", "max_epochs") if sizing.get(k) is None]
    if missing:
        raise ValueError(f"detector.epochs=auto needs detector.sizing.{missing[0]} (the budget it is sized to)")
    minutes, low, high = float(sizing["minutes"]), int(sizing["min_epochs"]), int(sizing["max_epochs"])
    if minutes <= 0 or not 1 <= low <= high:
        raise ValueError(f"detector.sizing: expected minutes > 0 and 1 <= min_epochs <= max_epochs, got {sizing}")
    probe = detector_epoch(cfg)
    if probe is None:  # e.g. data=word or a composed dataset: the images are counted only once the data stage ran
        return {"config": {"detector.epochs": high},
                "note": f"{high} epochs (detector.sizing.max_epochs): the data config names no image count to size "
                        "them by; detector.epochs=N sets them"}
    every = max(1, int(det.get("val_every_n_epochs", 1)))
    per_epoch = probe["epoch_s"] + probe["validation_s"] / every
    fits = int(60.0 * minutes // per_epoch) if per_epoch > 0 else high
    epochs = min(high, max(low, fits))
    bound = " (the most: detector.sizing.max_epochs)" if fits >= high else \
        " (the least: detector.sizing.min_epochs; over the budget)" if fits < low else ""
    return {"config": {"detector.epochs": epochs},
            "note": f"{epochs} epochs{bound} fit {minutes:g} min at ~{per_epoch:.0f} s an epoch: {probe['how']}"}


def _loader_item_seconds(cfg: DictConfig, det: dict) -> float:
    """Seconds the training loader spends on one item (``CenterNetDataset.__getitem__``: augmentation and
    targets) over images of the data's size letterboxed to the input, with MEAN_OBJECTS boxes each. The images are
    synthetic (the data need not exist yet), so the one-off decoding before training is not in it."""
    from deepword.word_format import Record
    from stages.detector.dataset import CenterNetDataset
    from stages.detector.model import model_config

    size = _plain(OmegaConf.select(cfg, "data.image_size", default=None)) or [det["input_width"], det["input_height"]]
    width, height = int(size[0]), int(size[1])
    rng = np.random.default_rng(0)
    n = MEAN_OBJECTS
    x1, y1 = rng.uniform(0, width * 0.9, n), rng.uniform(0, height * 0.9, n)
    boxes = np.column_stack([x1, y1, np.minimum(x1 + rng.uniform(10, 120, n), width),
                             np.minimum(y1 + rng.uniform(10, 80, n), height), np.ones(n),
                             rng.integers(0, 2, n), np.arange(n)])
    record = Record(image="probe.png", frame_id=0, camera="probe", width=width, height=height, boxes=boxes,
                    relations=[], wheel_pairs=[])
    dataset = CenterNetDataset(".", [record] * 8, int(det["input_width"]), int(det["input_height"]), n,
                               augment=det["augment"], min_overlap=det["min_overlap"],
                               regression=model_config(det)["regression"])
    image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    for i in range(len(dataset)):
        dataset.hold(i, image)
    batch = max(1, int(det["batch_size"]))
    # a batch's items per timed step: the mosaic's share of items (four images each) averages out within it
    return timed_steps(lambda: [dataset[i % len(dataset)] for i in range(batch)]) / batch


def _detector_targets(det: dict, batch: int, width: int, height: int, device) -> dict:
    import torch

    from stages.detector.model import CLASS_NAMES, DOWN_RATIO
    from stages.detector.targets import centernet_targets, facing_targets, ttfnet_box_targets

    rng = np.random.default_rng(0)
    items, n = [], MEAN_OBJECTS
    for _ in range(batch):
        x1, y1 = rng.uniform(0, width - 40, n), rng.uniform(0, height - 30, n)
        boxes = np.column_stack([x1, y1, x1 + rng.uniform(8, 40, n), y1 + rng.uniform(8, 30, n)])
        item = centernet_targets(boxes / DOWN_RATIO, rng.integers(0, len(CLASS_NAMES), n), len(CLASS_NAMES),
                                 width // DOWN_RATIO, height // DOWN_RATIO, n, det["min_overlap"])
        if det.get("regression", "centernet") == "ttfnet":
            item |= ttfnet_box_targets(boxes, width // DOWN_RATIO, height // DOWN_RATIO, DOWN_RATIO)
        if det.get("facing"):  # every object with a facing: the head's backward pass timed too
            item |= facing_targets(np.tile([[1.0, 0.0]], (n, 1)), item["mask"])
        items.append(item)
    return {k: torch.from_numpy(np.stack([it[k] for it in items])).to(device) for k in items[0]}


# -- relation -------------------------------------------------------------------------------------------------


def relation(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the relation stage's training: ensemble members x epochs x train steps x (the probed step and the
    augmentation of its crops), plus a validation pass an epoch; with early stopping (``relation.train.patience``)
    ``RELATION_BEST_EPOCH`` + patience epochs a network (the configured epochs at most), what the quick data's
    networks ran."""
    import torch

    from deepword.relation_graph import InputConfig
    from stages.relation.augment import AugmentConfig, augment_crops
    from stages.relation.distill import DistillConfig
    from stages.relation.lightning import RelationModule, collate_graphs
    from stages.relation.model import ModelConfig, RelationNet
    from stages.training.memory_format import use_channels_last
    from stages.training.precision import BF16, resolve_precision

    train_images, val_images = split_images(cfg, "train"), split_images(cfg, "val")
    if train_images is None:
        return None
    rel, tr = cfg.relation, _plain(cfg.trainer)
    train = _plain(rel.train)
    limit = train.get("limit_train_images")
    train_images = min(train_images, int(limit)) if limit else train_images
    copies = int((train.get("detection_noise") or {}).get("copies", 0))
    train_images *= 1 + copies  # each image again as a detector might see it (stages/relation/simulate.py)
    limit_val = train.get("limit_val_images")
    val_images = min(val_images or 0, int(limit_val)) if limit_val else (val_images or 0)
    batch = int(train["batch_size"])
    precision = resolve_precision(tr.get("precision", "32-true"), tr.get("accelerator", "auto"))
    device, sync = _device(tr.get("accelerator", "auto"))
    in_cfg, model_cfg = InputConfig.from_cfg(rel), ModelConfig.from_cfg(rel)
    threads = int(train.get("threads") or 1)
    with _threads(threads):
        torch.manual_seed(0)
        channels_last = use_channels_last(bool(train["channels_last"]), RelationNet(model_cfg).backbone,
                                          precision == BF16, device.type != "cpu", "the relation backbone")
        module = RelationModule(model=dict(model_cfg.__dict__), loss=_plain(rel.loss), decode=_plain(rel.decode),
                                optim={"lr": 1e-3, "weight_decay": 0.0}, backbone_bf16=precision == BF16,
                                backbone_channels_last=channels_last)
        module = module.to(device).train()
        opt = torch.optim.AdamW(module.parameters(), lr=1e-3)
        items = _relation_items(batch, in_cfg.input_size)
        graphs = {k: v.to(device) for k, v in collate_graphs(items).items()}

        def step():
            loss = module._loss(module(graphs), graphs)["loss"]
            opt.zero_grad()
            loss.backward()
            opt.step()

        step_s = timed_steps(step, sync)
        module.eval()

        def forward():
            with torch.no_grad():
                module(graphs)

        forward_s = timed_steps(forward, sync)
        # the crops' appearance augmentation runs per image in the training process, beside the step (a third of
        # an fp32 epoch on a 2-core host): timed on the probe's batch, as GraphDataset applies it
        augment = AugmentConfig.from_cfg(_plain(rel.get("augment")))
        augment_s = timed_steps(lambda: [augment_crops(item["crops"], augment) for item in items]) \
            if augment.active else 0.0
    members, epochs = int(rel.get("ensemble", 1)), int(train["epochs"])
    # early stopping ends a network `patience` epochs after its best, which came in its 5th to 8th epoch on the quick
    # data: count RELATION_BEST_EPOCH + patience, the configured epochs at most (patience 8: 12-15 epochs were run,
    # 14 counted; patience 4: 8-10 run, 10 counted)
    expected = min(epochs, RELATION_BEST_EPOCH + int(train["patience"])) if train.get("patience") else epochs
    replicas = _replicas(tr)
    steps = math.ceil(math.ceil(train_images / replicas) / batch)
    val_batches = math.ceil(val_images / batch)
    epoch_s = steps * (step_s + augment_s) + val_batches * forward_s
    seconds = members * expected * epoch_s
    augmenting = f" + {1000 * augment_s:.0f} ms augmentation" if augment_s else ""
    student = ""
    if DistillConfig.from_cfg(rel.get("distill")).ships_student(members):
        # the student (relation.distill) trains as a member does, and each of its steps also runs the members forward
        seconds += expected * (epoch_s + steps * members * forward_s)
        student = f" + a student taught by them (+{members} x {1000 * forward_s:.0f} ms forward a step)"
    return {"seconds": seconds,
            "note": f"{members} network(s){student} x {expected if expected == epochs else f'~{expected} of {epochs}'} epochs x ({steps} steps x ({1000 * step_s:.0f} ms{augmenting}) + "
                    f"{val_batches} "
                    f"val batches) ({_precision_name(precision, channels_last)} backbone, batch {batch}, {threads} "
                    "threads); early stopping (patience "
                    f"{train.get('patience')}) decides the epochs",
            "hint": f"~{epoch_s:.0f} s an epoch a network: fewer epochs (relation.train.epochs=N, now {epochs}) or "
                    f"networks (relation.ensemble, now {members}), or a GPU (trainer=gpu)"}


def _relation_items(batch: int, size: int) -> list[dict]:
    import torch

    rng = np.random.default_rng(0)
    items = []
    for n in rng.integers(2, 2 * MEAN_OBJECTS - 1, batch):
        n = int(n)
        classes = (np.arange(n) % 3 != 0).astype(np.int64)  # a third vehicles, the rest wheels
        cand = classes[:, None] + classes[None, :] >= 1
        np.fill_diagonal(cand, False)
        adj = np.where(cand, rng.random((n, n)), 0).astype(np.float32)
        np.fill_diagonal(adj, 1.0)
        owner = np.zeros((n, n), np.uint8)
        wheels, vehicles = np.flatnonzero(classes == 1), np.flatnonzero(classes == 0)
        if len(vehicles):
            owner[wheels, vehicles[wheels % len(vehicles)]] = 1
        items.append({"crops": torch.from_numpy(rng.integers(0, 256, (n, 3, size, size), dtype=np.uint8)),
                      "coords": torch.from_numpy(rng.random((n, 4), dtype=np.float32)),
                      "classes": torch.from_numpy(classes), "valid": torch.ones(n, dtype=torch.bool),
                      "adj": torch.from_numpy(adj), "cand": torch.from_numpy(cand),
                      "owner": torch.from_numpy(owner), "couple": torch.zeros((n, n), dtype=torch.uint8),
                      "role": torch.full((n,), -1, dtype=torch.long)})
    return items


VEHICLE_SHARE = 1 / 3   # of an image's objects (MEAN_OBJECTS), as the relation probe draws them


def facing(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the facing stage's training: epochs x train steps x the probed step (every train vehicle twice, as
    labelled and with its box jittered), plus a flip-averaged val pass an epoch. An upper bound: only vehicles with 3D
    truth train, and the images per split are the configured ones before the generator drops any."""
    import torch

    from stages.facing.model import FacingNet, facing_loss
    from stages.training.memory_format import use_channels_last
    from stages.training.precision import BF16, resolve_precision

    train_images, val_images = split_images(cfg, "train"), split_images(cfg, "val")
    if train_images is None:
        return None
    fc, tr = _plain(cfg.facing), _plain(cfg.trainer)
    limit = fc["train"].get("limit_train_images")
    train_images = min(train_images, int(limit)) if limit else train_images
    per_image = MEAN_OBJECTS * VEHICLE_SHARE
    copies = 2 if float(fc["train"]["box_jitter"]) > 0 else 1
    train_crops, val_crops = train_images * per_image * copies, (val_images or 0) * per_image
    batch, size = int(fc["train"]["batch_size"]), int(fc["input_size"])
    precision = resolve_precision(tr.get("precision", "32-true"), tr.get("accelerator", "auto"))
    device, sync = _device(tr.get("accelerator", "auto"))
    threads = int(fc["train"].get("threads") or 1)
    with _threads(threads):
        torch.manual_seed(0)
        net = FacingNet(tuple(fc["widths"]), int(fc["hidden"]), fc.get("convs"))
        channels_last = use_channels_last(bool(fc["train"]["channels_last"]), net, precision == BF16,
                                          device.type != "cpu", "the facing network")
        fmt = torch.channels_last if channels_last else torch.contiguous_format
        net = net.to(device).to(memory_format=fmt).train()
        opt = torch.optim.AdamW(net.parameters(), lr=1e-3)
        crops = torch.randint(0, 256, (batch, 3, size, size), dtype=torch.uint8,
                              device=device).contiguous(memory_format=fmt)
        targets = torch.nn.functional.normalize(torch.randn(batch, 2, device=device), dim=1)

        def step():
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == BF16):
                loss = facing_loss(net(crops).float(), targets)
            opt.zero_grad()
            loss.backward()
            opt.step()

        step_s = timed_steps(step, sync)
        net.eval()

        def forward():
            with torch.no_grad():
                net(crops)

        forward_s = timed_steps(forward, sync)
    epochs = int(fc["train"]["epochs"])
    steps = math.ceil(train_crops / batch)
    epoch_s = steps * step_s + 2 * math.ceil(val_crops / batch) * forward_s
    return {"seconds": epochs * epoch_s,
            "note": f"{epochs} epochs x ({steps} steps x {1000 * step_s:.0f} ms + val) "
                    f"({_precision_name(precision, channels_last)}, batch {batch}, {threads} threads); at most: only "
                    "vehicles with 3D truth train",
            "hint": f"~{epoch_s:.0f} s an epoch: fewer epochs (facing.train.epochs=N, now {epochs}), "
                    "facing.train.box_jitter=0 (one copy of each vehicle), or a GPU (trainer=gpu)"}


# The generator's first rig is probed: its first frame builds the rig's per-pixel tables (about a frame's rendering
# again), the others render with them; at most this many frames (~1 s on a 2-core host)
RENDER_PROBE_FRAMES = 4


def data(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the data stage (``data=synword``): the generator's frames, each rendered and written as probed here
    on the first rig's frames, shared among the stage's processes. None for a dataset read from disk or composed of
    sources (``data.sources``)."""
    return _rendering(_plain(cfg.data), int(cfg.seed), "data")


def shift_data(cfg: DictConfig, context=None) -> dict | None:
    """Seconds of the held-out test set's generation (``shift.data``), as ``data``."""
    return _rendering(_plain(cfg.shift.data), int(cfg.seed), "shift.data")


def _rendering(dcfg: dict, seed: int, key: str) -> dict | None:
    import cv2

    from stages.data.synword import PNG_PARAMS, FrameGenerator, renderer_processes

    if dcfg.get("sources") is not None or dcfg.get("name") != "synword":
        return None
    frames, per_rig = int(dcfg["frames"]), int(dcfg["lens"]["frames_per_rig"])
    probed = max(1, min(RENDER_PROBE_FRAMES, per_rig, frames))
    started = time.perf_counter()
    gen = FrameGenerator(dcfg, seed)
    setup_s = time.perf_counter() - started
    render_s, write_s = [], 0.0
    for frame_id in range(probed):
        t = time.perf_counter()
        views = gen.render_frame(frame_id)
        render_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        for _, img, _ in views:   # as the stage writes them (stages.data.synword.write_frame)
            cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), PNG_PARAMS)
        write_s += time.perf_counter() - t
    # a frame on average: the rig's first frame once per rig, the others as the probe's later frames rendered
    later = statistics.mean(render_s[1:]) if probed > 1 else render_s[0]
    frame_s = (render_s[0] + (per_rig - 1) * later) / per_rig + write_s / probed
    workers = renderer_processes(dcfg.get("workers"), frames)
    seconds = setup_s + math.ceil(frames / workers) * frame_s
    return {"seconds": seconds,
            "note": f"{frames} frames x {1000 * frame_s:.0f} ms (rendered and written; a rig's tables "
                    f"{1000 * max(0.0, render_s[0] - later):.0f} ms every {per_rig} frames) / {workers} processes",
            "hint": f"fewer frames ({key}.frames=N, now {frames}) or more cores"}
