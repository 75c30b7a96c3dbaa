"""Stage ``facing``: the facing network (``model.FacingNet``) trained on the vehicle crops of the train split that
have a facing target (``targets.facing_targets``: the 3D truth where a record has it, else a labelled couple's
rear and front roles), chosen by val accuracy (docs/bev.md, "Front and back").

What it writes: ``facing.json`` (its input settings, val accuracy, where its targets came from, curves;
``trained: false`` where train or val has no target to learn from, e.g. 2D labels without roles: then no network and
no vectors), ``facing.pt`` (the weights, when trained), ``artifacts/facing_curves.png``. The export stage ships it in
the bundle as ``facing.onnx``; the bev stage and ``deepword infer --calibration`` read each vehicle's vector from
there.

Each train vehicle is seen as labelled and once more with its box sides jittered by ``facing.train.box_jitter`` x its
size (a detector's box); training crops are mirrored with probability one half (the vector's x negated) and their
brightness and white balance jittered."""

from __future__ import annotations

import json
import logging
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

from deepword.facing import box_facings
from deepword.facing_crop import to_crop
from deepword.relation_graph import crop_objects
from deepword.word_format import load_image, open_dataset
from stages.facing.targets import count_targets, facing_targets, target_settings
from stages.training.lightning_logs import format_duration

log = logging.getLogger(__name__)

CONFIG_FILE = "facing.json"
WEIGHTS_FILE = "facing.pt"


def split_crops(records, root, size: int, margin: float, jitter: float, rng: np.random.Generator | None,
                limit: int | None = None, pad: int = 0, targets_of=box_facings) -> tuple[np.ndarray, np.ndarray]:
    """Crops (M, 3, size + 2 pad, size + 2 pad) uint8 and crop-pixel unit targets (M, 2) of every vehicle with a
    facing target (``targets_of(record)``: (N, 2) per box, NaN for none; ``deepword.facing.box_facings``, the 3D truth,
    by default) in ``records``; with ``rng`` each also once more with its box jittered. With ``pad`` the crop reaches
    ``pad`` pixels further on each side at the same scale, so that its central ``size`` window is the crop a margin of
    ``margin`` gives (``augment`` moves that window); a direction in the crop does not depend on the margin (the box
    grows alike in width and height)."""
    if pad:
        margin, size = ((1 + 2 * margin) * (size + 2 * pad) / size - 1) / 2, size + 2 * pad
    crops, targets = [], []
    for rec in records[:limit] if limit else records:
        facings = targets_of(rec)
        rows = np.flatnonzero(np.isfinite(facings).all(axis=1))
        if len(rows) == 0:
            continue
        rgb = load_image(root, rec)
        boxes = rec.xyxy[rows]
        views = [boxes]
        if rng is not None and jitter > 0:
            wh = boxes[:, 2:] - boxes[:, :2]
            views.append(boxes + rng.uniform(-jitter, jitter, boxes.shape) * np.concatenate([wh, wh], axis=1))
        for view in views:
            crops.append(crop_objects(rgb, view, size, margin))
            targets.append(to_crop(facings[rows], view, margin))
    if not crops:
        return np.zeros((0, 3, size, size), np.uint8), np.zeros((0, 2), np.float32)
    return np.concatenate(crops), np.concatenate(targets)


def run(cfg, inputs: dict[str, Path], out_dir: Path) -> dict[str, float]:
    import torch

    # imported here: they load torch, which importing this module must not
    from stages.facing.model import FacingNet, facing_loss
    from stages.training.memory_format import use_channels_last
    from stages.training.precision import resolve_precision, trains_on_gpu

    started = time.perf_counter()
    out_dir = Path(out_dir)
    fc, tc = cfg.facing, cfg.facing.train
    seed, epochs = int(tc.seed), int(tc.epochs)
    torch.set_num_threads(int(tc.threads))
    ds = open_dataset(inputs["data"])
    size, margin = int(fc.input_size), float(fc.margin)
    rng = np.random.default_rng(seed)
    shift = float(tc.get("shift", 0.0))   # absent (older configs): no shift
    if shift < 0:
        raise ValueError(f"facing.train.shift: a share of the crop side, 0 or more (0: no shift), got {shift}")
    pad = round(shift * size)
    targets = target_settings(fc)
    train_records, val_records = ds.subset("train"), ds.subset("val")
    limit = tc.get("limit_train_images")
    train_x, train_y = split_crops(train_records, ds.root, size, margin, float(tc.box_jitter), rng, limit, pad,
                                   partial(facing_targets, **targets))
    val_x, val_y = split_crops(val_records, ds.root, size, margin, 0.0, None,
                               targets_of=partial(facing_targets, **targets))
    # vehicles with a target by where it came from, each image once (a composed train split repeats some)
    sources = {split: count_targets(list({r.image: r for r in recs}.values()), **targets)
               for split, recs in (("train", train_records[:limit] if limit else train_records),
                                   ("val", val_records))}
    convs = fc.get("convs")   # absent (older configs): FacingNet's two a block
    settings = {"input_size": size, "margin": margin, "widths": list(fc.widths), "hidden": int(fc.hidden),
                "convs": None if convs is None else [int(n) for n in convs]}
    if len(train_x) == 0 or len(val_x) == 0:
        reason = (f"no vehicles with a facing target (3D truth: calibration and objects_3d; or a couple labelled rear "
                  f"and front) to learn from: {len(train_x)} train, {len(val_x)} val crops")
        log.warning("facing: %s; no facing network (the footprints' headings come from the roles and the prior)",
                    reason)
        (out_dir / CONFIG_FILE).write_text(json.dumps({**settings, "trained": False, "reason": reason}, indent=1))
        return {"facing.trained": 0.0}

    device = torch.device("cuda" if trains_on_gpu(cfg.trainer.accelerator) else "cpu")
    bf16 = resolve_precision(str(cfg.trainer.precision), cfg.trainer.accelerator).startswith("bf16")
    torch.manual_seed(seed)
    net = FacingNet(tuple(int(w) for w in fc.widths), int(fc.hidden), settings["convs"])
    channels_last = use_channels_last(bool(tc.channels_last), net, bf16, device.type == "cuda", "the facing network")
    layout = torch.channels_last if channels_last else torch.contiguous_format
    net = net.to(device).to(memory_format=layout)
    batch = int(tc.batch_size)
    steps = epochs * ((len(train_x) + batch - 1) // batch)
    opt = torch.optim.AdamW(net.parameters(), lr=float(tc.lr), weight_decay=float(tc.weight_decay))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, float(tc.lr), total_steps=steps)
    xs, ys = torch.from_numpy(train_x), torch.from_numpy(train_y)
    gen = torch.Generator().manual_seed(seed)
    history, best = [], (-1.0, 0, None)
    for epoch in range(epochs):
        t0 = time.perf_counter()
        net.train()
        total = 0.0
        for idx in torch.randperm(len(xs), generator=gen).split(batch):
            x, y = augment(xs[idx], ys[idx], gen, size)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
                loss = facing_loss(net(x.to(device).contiguous(memory_format=layout)).float(), y.to(device))
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(idx)
        acc = 100.0 * float(np.mean(agreement(net, val_x, val_y, device) > 0))
        history.append({"epoch": epoch, "train/loss": total / len(xs), "val/facing_acc": acc})
        # a tie goes to the later epoch: on a val split of a few dozen vehicles (a team's own) the accuracy ties
        # often, and the one-cycle schedule's later epochs are the better trained
        if acc >= best[0]:
            best = (acc, epoch, {k: v.detach().cpu().clone() for k, v in net.state_dict().items()})
        left = (time.perf_counter() - started) / (epoch + 1) * (epochs - epoch - 1)
        print(f"facing epoch {epoch + 1}/{epochs}: train/loss={total / len(xs):.4g} val/facing_acc={acc:.2f} "
              f"({time.perf_counter() - t0:.0f} s" + (f", ~{format_duration(left)} left)" if left > 0 else ")"),
              file=sys.stderr, flush=True)
    acc, best_epoch, state = best
    torch.save(state, out_dir / WEIGHTS_FILE)
    net.load_state_dict(state)
    scale, nll = logit_scale(agreement(net, val_x, val_y, device))
    (out_dir / CONFIG_FILE).write_text(json.dumps({
        **settings, "trained": True, "val_acc": acc, "logit_scale": scale, "val_nll": nll, "best_epoch": best_epoch,
        "seed": seed, "bf16": bf16, "channels_last": channels_last, "train_crops": len(train_x),
        "val_vehicles": len(val_x), "targets": {**targets, "roles_only": list(targets["roles_only"])},
        "target_sources": sources, "curves": history},
        indent=1))
    plot_curves(history, out_dir / "artifacts" / "facing_curves.png")
    return {"facing.trained": 1.0, "facing.val.acc": acc, "facing.val.vehicles": float(len(val_x)),
            "facing.val.logit_scale": scale, "facing.val.nll": nll,
            "facing.train.crops": float(len(train_x)), "facing.best_epoch": float(best_epoch),
            **{f"facing.{split}.targets_{source}": float(n) for split, counts in sources.items()
               for source, n in counts.items()},
            "facing.epochs": float(epochs), "facing.params": float(sum(p.numel() for p in net.parameters())),
            "facing.bf16": float(bf16), "facing.channels_last": float(channels_last),
            "facing.train.seconds": time.perf_counter() - started}


BRIGHTNESS, CHANNEL_GAIN = 0.3, 0.1


def augment(crops, targets, gen, size: int | None = None):
    """A training batch: from crops larger than ``size`` (``split_crops``' pad) a ``size`` window of each at a random
    place (a translation: the target's direction holds), each mirrored with probability 1/2 (its target's x negated),
    its brightness scaled by 1 +- BRIGHTNESS and each channel by 1 +- CHANNEL_GAIN (white balance); float crops in
    0-255."""
    import torch

    spare = crops.shape[-1] - (size or crops.shape[-1])
    if spare > 0:
        b, window = len(crops), torch.arange(size)
        ox, oy = torch.randint(0, spare + 1, (2, b), generator=gen)
        crops = crops[torch.arange(b)[:, None, None, None], torch.arange(3)[None, :, None, None],
                      (oy[:, None] + window)[:, None, :, None], (ox[:, None] + window)[:, None, None, :]]
    x, y = crops.to(torch.float32), targets.clone()
    flip = torch.rand(len(x), generator=gen) < 0.5
    x[flip] = x[flip].flip(-1)
    y[flip, 0] = -y[flip, 0]
    gain = 1 + BRIGHTNESS * (2 * torch.rand(len(x), 1, 1, 1, generator=gen) - 1)
    gain = gain * (1 + CHANNEL_GAIN * (2 * torch.rand(len(x), 3, 1, 1, generator=gen) - 1))
    return (x * gain).clamp(0, 255), y


def agreement(net, crops: np.ndarray, targets: np.ndarray, device, batch: int = 256) -> np.ndarray:
    """<vector, target> per crop, the vectors flip-averaged as inference takes them (``OnnxFacing``)."""
    import torch

    net.eval()
    out = []
    with torch.no_grad():
        for start in range(0, len(crops), batch):
            x = torch.from_numpy(crops[start:start + batch]).to(device)
            v = (net(x) + net(x.flip(-1)) * torch.tensor([-1.0, 1.0], device=device)) / 2
            out.append((v.float().cpu().numpy() * targets[start:start + batch]).sum(1))
    return np.concatenate(out)


SCALE_GRID = np.logspace(-2, 1.5, 71)


def logit_scale(projections: np.ndarray) -> tuple[float, float]:
    """The factor ``k`` that makes ``k x <vector, direction>`` the log-odds that a vehicle's front lies along
    ``direction`` (temperature scaling): the one of ``SCALE_GRID`` with the least mean negative log-likelihood of the
    val vehicles' true directions (``projections``: <vector, truth> each), and that likelihood. Trained to a small loss,
    the vectors are longer than their accuracy warrants; scaled, a vehicle the network is unsure of votes little."""
    p = np.asarray(projections, dtype=np.float64)
    nll = [float(np.mean(np.logaddexp(0.0, -k * p))) for k in SCALE_GRID]
    best = int(np.argmin(nll))
    return float(SCALE_GRID[best]), nll[best]


def load_network(stage_dir: str | Path):
    """The trained FacingNet in eval mode on the CPU and its facing.json; (None, meta) where none was trained."""
    import torch

    from stages.facing.model import FacingNet

    stage_dir = Path(stage_dir)
    meta = json.loads((stage_dir / CONFIG_FILE).read_text())
    if not meta.get("trained"):
        return None, meta
    net = FacingNet(tuple(meta["widths"]), int(meta["hidden"]), meta.get("convs"))  # None: two a block
    net.load_state_dict(torch.load(stage_dir / WEIGHTS_FILE, map_location="cpu", weights_only=True))
    return net.eval(), meta


def plot_curves(history: list[dict], path: Path) -> Path:
    """Train loss and val accuracy over epochs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, (ax_loss, ax_acc) = plt.subplots(1, 2, figsize=(9, 3.5))
    epochs = [r["epoch"] + 1 for r in history]
    ax_loss.plot(epochs, [r["train/loss"] for r in history], marker="o", ms=3)
    ax_loss.set_xlabel("epoch")
    ax_loss.set_title("train loss (logistic on the projection)")
    ax_acc.plot(epochs, [r["val/facing_acc"] for r in history], marker="o", ms=3, color="tab:green")
    ax_acc.set_xlabel("epoch")
    ax_acc.set_ylabel("%")
    ax_acc.set_title("val accuracy (vector within 90 deg of the truth)")
    ax_acc.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
