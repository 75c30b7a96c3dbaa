"""Training curves of the relation network: a Lightning callback that records them per epoch and a
PNG of loss and val wheel_acc, logged with the stage's artifacts."""

from __future__ import annotations

from pathlib import Path

import lightning as L


class CurveHistory(L.Callback):
    """Per epoch: train/loss, val/loss, val/wheel_acc. Read at the end of the training epoch, when Lightning
    has reduced the epoch's train loss and the epoch's validation has run."""

    def __init__(self):
        self.rows: list[dict[str, float]] = []

    def on_train_epoch_end(self, trainer, pl_module):
        m = trainer.callback_metrics
        row = {"epoch": float(trainer.current_epoch)}
        for key in ("train/loss", "val/loss", "val/wheel_acc"):
            if key in m:
                row[key] = float(m[key])
        self.rows.append(row)

    # Saved in every checkpoint: a resumed run keeps its earlier epochs, and under ddp_spawn (training in
    # child processes) the main process reads the curves back from rank 0's last checkpoint.
    def state_dict(self) -> dict:
        return {"rows": list(self.rows)}

    def load_state_dict(self, state_dict: dict) -> None:
        self.rows = list(state_dict["rows"])


def plot_curves(rows: list[dict[str, float]], path: Path,
                loss_title: str = "loss (weighted L2 + role + owner ranking)") -> Path:
    """Two panels: losses (log scale) and val wheel_acc (percent) over epochs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, (ax_loss, ax_acc) = plt.subplots(1, 2, figsize=(9, 3.5))
    for key, label in (("train/loss", "train loss"), ("val/loss", "val loss")):
        pts = [(r["epoch"], r[key]) for r in rows if key in r]
        if pts:
            ax_loss.plot(*zip(*pts, strict=True), marker="o", ms=3, label=label)
    ax_loss.set_yscale("log")
    ax_loss.set_xlabel("epoch")
    ax_loss.set_title(loss_title)
    ax_loss.legend()
    pts = [(r["epoch"], r["val/wheel_acc"]) for r in rows if "val/wheel_acc" in r]
    if pts:
        ax_acc.plot(*zip(*pts, strict=True), marker="o", ms=3, color="tab:green")
    ax_acc.set_xlabel("epoch")
    ax_acc.set_ylabel("%")
    ax_acc.set_title("val wheel_acc")
    ax_acc.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
