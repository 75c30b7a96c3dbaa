"""The checkpoint callbacks every training stage uses: the best epoch by a monitored metric, and the latest
epoch (``last.ckpt``) for resuming after a crash and for reading back what ``ddp_spawn`` ranks trained; and
the optional weight averaging whose weights those checkpoints then hold.

Lightning's own ``save_last=True`` writes ``last.ckpt`` only in epochs that also saved a best
checkpoint, so after an epoch without improvement it would hold an older epoch: resuming would repeat
work and the curves read back from it would miss epochs. The latest epoch therefore has its own
unmonitored callback."""

from __future__ import annotations

from pathlib import Path

LAST = "last"


def best_and_latest(ckpt_dir: Path, monitor: str, mode: str, best_name: str = "best") -> tuple:
    """(best-epoch callback ``<best_name>.ckpt``, latest-epoch callback ``last.ckpt``)."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    best = ModelCheckpoint(dirpath=ckpt_dir, filename=best_name, monitor=monitor, mode=mode,
                           auto_insert_metric_name=False)
    latest = ModelCheckpoint(dirpath=ckpt_dir, filename=LAST, monitor=None, save_top_k=1, enable_version_counter=False)
    return best, latest


def weight_averaging(decay: float, multi_tensor: bool = False) -> list:
    """``[]`` for decay 0, else a Lightning ``WeightAveraging`` callback: an exponential moving average of the weights
    (and of BatchNorm's statistics), updated after every optimiser step with this decay. Training goes on with
    the raw weights; validation, and so checkpoint selection, and every checkpoint's ``state_dict``, and so what
    a stage ships, hold the average.

    ``multi_tensor``: one ``torch._foreach_lerp_`` over all the tensors a step (torch's ``get_ema_multi_avg_fn``)
    instead of ``EMAWeightAveraging``'s update of one tensor after another: the same average, rounded differently,
    at 2.5-6x less cost on the detector's 148 tensors (~2 ms against 6-11 ms a step on 2 cores; ``make bench``
    prints both). The relation stage keeps the per-tensor update: its ten-dataset comparison was measured with
    it, and the update is a small part of its steps."""
    if not 0 <= decay < 1:
        raise ValueError(f"weight averaging: decay must be in [0, 1), got {decay}")
    if decay == 0:
        return []
    if multi_tensor:
        from lightning.pytorch.callbacks import WeightAveraging
        from torch.optim.swa_utils import get_ema_multi_avg_fn

        # WeightAveraging updates after every optimiser step, as EMAWeightAveraging does by default
        return [WeightAveraging(multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)]
    from lightning.pytorch.callbacks import EMAWeightAveraging

    return [EMAWeightAveraging(decay=decay)]
