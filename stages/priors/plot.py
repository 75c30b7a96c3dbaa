"""Fig. 4-style figure: histograms of log distance ratio for true pairs and non-pairs, with the fitted
densities, one panel per pair type."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepword.priors import Mixture1D, log_ratio
from stages.priors.pairs import LabelledRatios

TITLES = {"wheel_vehicle": "wheel-vehicle (A = vehicle, B = wheel)",
          "wheel_wheel": "wheel-wheel (A = rear, B = front wheel)"}


def plot_priors(path: Path, ratios: dict[str, LabelledRatios], fits: dict[str, tuple[Mixture1D, Mixture1D | None]],
                bins: int = 60) -> None:
    """Write the figure to ``path`` (PNG). ``fits`` maps pair type -> (pair mixture, non-pair mixture)."""
    import matplotlib

    matplotlib.use("Agg")  # headless: stages run without a display
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(ratios), figsize=(6 * len(ratios), 4.2), squeeze=False)
    for ax, (kind, lab) in zip(axes[0], ratios.items(), strict=True):
        pos, neg = log_ratio(lab.pairs), log_ratio(lab.non_pairs)
        # the range covers both populations' bulk (pairs are far fewer: a joint percentile would cut them)
        ranges = [np.percentile(x, [0.5, 99.5]) for x in (pos, neg) if len(x)]
        lo, hi = (min(r[0] for r in ranges), max(r[1] for r in ranges)) if ranges else (-1.0, 1.0)
        edges = np.linspace(lo, hi, bins + 1)
        if len(neg):
            ax.hist(neg, bins=edges, density=True, alpha=0.35, color="tab:gray", label=f"non-pairs (n={len(neg)})")
        if len(pos):
            ax.hist(pos, bins=edges, density=True, alpha=0.55, color="tab:blue", label=f"pairs (n={len(pos)})")
        grid = np.linspace(lo, hi, 400)
        pair_fit, non_fit = fits[kind]
        ax.plot(grid, pair_fit.pdf(grid), color="tab:red", lw=2,
                label=f"pair GMM ({len(pair_fit.weights)} comp.)")
        if non_fit is not None:
            ax.plot(grid, non_fit.pdf(grid), color="black", lw=1.5, ls="--",
                    label=f"non-pair GMM ({len(non_fit.weights)} comp.)")
        ax.set_title(TITLES.get(kind, kind))
        ax.set_xlabel("log(distance ratio)  [Eq. 2]")
        ax.set_ylabel("density")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
