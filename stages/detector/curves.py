"""Training curves (loss and val AP per epoch) from Lightning's CSV log, as a PNG."""

from __future__ import annotations

import csv
from pathlib import Path


def read_curves(metrics_csv: str | Path) -> dict[str, list[tuple[float, float]]]:
    """``{metric: [(epoch, value), ...]}`` from a CSVLogger ``metrics.csv`` (rows hold subsets of metrics)."""
    curves: dict[str, list[tuple[float, float]]] = {}
    with open(metrics_csv, newline="") as fh:
        for row in csv.DictReader(fh):
            epoch = row.get("epoch")
            for key, value in row.items():
                if key in ("epoch", "step") or value in ("", None) or epoch in ("", None):
                    continue
                curves.setdefault(key, []).append((float(epoch), float(value)))
    return curves


def plot_curves(metrics_csv: str | Path, path: str | Path) -> None:
    """Left: training and val loss; right: val AP@0.5 per class, both against the epoch."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = read_curves(metrics_csv)
    fig, (ax_loss, ax_ap) = plt.subplots(1, 2, figsize=(10, 3.8))
    for key in ("train/loss_epoch", "val/loss"):
        if key in curves:
            xs, ys = zip(*curves[key], strict=True)
            ax_loss.plot(xs, ys, ".-" if key.startswith("val") else "-", label=key, alpha=0.8)
    ax_loss.set(xlabel="epoch", ylabel="loss", yscale="log", title="CenterNet loss")
    for key in ("val/ap50.vehicle", "val/ap50.wheel", "val/ap.vehicle", "val/ap.wheel"):
        if key in curves:
            xs, ys = zip(*curves[key], strict=True)
            ax_ap.plot(xs, ys, ".-", label=key)
    ax_ap.set(xlabel="epoch", ylabel="AP (%)", ylim=(0, 100), title="val AP")
    for ax in (ax_loss, ax_ap):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
