"""What the operating-point search saw, for people: ``artifacts/operating_point.{png,md}`` of the export stage
(scored on the val split) and of ``deepword tune`` (on a user's labelled images).

The search (``deepword.operating_point.search``) scores every point of a grid and keeps one. Whether that one
stands on a plateau or on a ridge, and how much a threshold a little off would cost, is what a user tuning the
bundle for other images wants to know; a table of 6,760 numbers does not say it, two heat maps do:

- left: the search's criterion (``CRITERION``, pair_f1) over the two classes' score thresholds, at the chosen minimum box sides;
- right: the criterion over the two classes' minimum box sides, at the chosen thresholds.

Both are cuts through the chosen point, which each marks. The markdown gives the chosen point, the best points of
the search and the score with everything kept.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from deepword.operating_point.search import CRITERION, OperatingPoint

__all__ = ["side_surface", "threshold_surface", "operating_point_markdown", "plot_operating_point",
           "write_operating_point_report"]


def _surface(seen: Mapping[OperatingPoint, float], axis: str, fixed: tuple[float, ...]
             ) -> tuple[list[float], list[float], np.ndarray]:
    """(first class's values, second class's values, criterion[i_second, j_first]) over ``axis`` (``thresholds`` or
    ``min_sides``) of the two-class points whose other axis equals ``fixed``; NaN where a point was not scored."""
    other = "min_sides" if axis == "thresholds" else "thresholds"
    cut = {getattr(p, axis): f1 for p, f1 in seen.items() if getattr(p, other) == fixed}
    if not cut or any(len(k) != 2 for k in cut):
        raise ValueError(f"operating point report: no two-class points with {other} = {fixed}")
    xs = sorted({k[0] for k in cut})
    ys = sorted({k[1] for k in cut})
    grid = np.full((len(ys), len(xs)), np.nan)
    for (x, y), f1 in cut.items():
        grid[ys.index(y), xs.index(x)] = f1
    return xs, ys, grid


def threshold_surface(seen: Mapping[OperatingPoint, float], min_sides: tuple[float, ...]):
    """val ``CRITERION`` over both classes' score thresholds at ``min_sides``: (first class's thresholds, second
    class's thresholds, grid[second, first])."""
    return _surface(seen, "thresholds", tuple(min_sides))


def side_surface(seen: Mapping[OperatingPoint, float], thresholds: tuple[float, ...]):
    """val ``CRITERION`` over both classes' minimum box sides at ``thresholds``: (first class's sides, second class's
    sides, grid[second, first])."""
    return _surface(seen, "min_sides", tuple(thresholds))


def _heatmap(ax, xs, ys, grid, chosen_xy, xlabel: str, ylabel: str, title: str, fmt: str) -> object:
    from matplotlib.patches import Rectangle

    finite = grid[np.isfinite(grid)]
    image = ax.imshow(grid, origin="lower", cmap="viridis", aspect="auto",
                      vmin=float(finite.min()), vmax=float(finite.max()))
    ax.set_xticks(range(len(xs)), [fmt.format(x) for x in xs], rotation=90 if len(xs) > 8 else 0)
    ax.set_yticks(range(len(ys)), [fmt.format(y) for y in ys])
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    best = float(finite.max())
    if grid.size <= 200:   # the numbers, where they still fit
        for i, j in zip(*np.nonzero(np.isfinite(grid)), strict=True):
            ax.text(j, i, f"{grid[i, j]:.1f}", ha="center", va="center", fontsize=6,
                    color="black" if grid[i, j] > best - 0.35 * (best - finite.min()) else "white")
    cx, cy = xs.index(chosen_xy[0]), ys.index(chosen_xy[1])
    ax.add_patch(Rectangle((cx - 0.5, cy - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=2))
    return image


def plot_operating_point(seen: Mapping[OperatingPoint, float], chosen: OperatingPoint, classes: Sequence[str],
                         path: str | Path, method: str = "", images: str = "the val split") -> None:
    """The two cuts through ``chosen`` (module docstring) as one PNG; the chosen point framed in red. ``images``
    says what the points were scored on."""
    if len(classes) != 2:
        raise ValueError(f"operating point plot: needs two classes, got {list(classes)}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = classes
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5.6), gridspec_kw={"width_ratios": [1.5, 1]})
    xs, ys, grid = threshold_surface(seen, chosen.min_sides)
    image = _heatmap(left, xs, ys, grid, chosen.thresholds, f"{a} score threshold", f"{b} score threshold",
                     f"at minimum sides {a} {chosen.min_sides[0]:g} px, {b} {chosen.min_sides[1]:g} px", "{:.2f}")
    fig.colorbar(image, ax=left, label=f"{CRITERION} (%)")
    xs, ys, grid = side_surface(seen, chosen.thresholds)
    image = _heatmap(right, xs, ys, grid, chosen.min_sides, f"{a} minimum box side (px)",
                     f"{b} minimum box side (px)",
                     f"at score thresholds {a} {chosen.thresholds[0]:.2f}, {b} {chosen.thresholds[1]:.2f}", "{:g}")
    fig.colorbar(image, ax=right, label=f"{CRITERION} (%)")
    fig.suptitle(f"Operating point: end-to-end {CRITERION}{' of ' + method if method else ''} on {images} "
                 f"(chosen: {seen[chosen]:.2f}, framed)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def operating_point_markdown(seen: Mapping[OperatingPoint, float], chosen: OperatingPoint, classes: Sequence[str],
                             at_score_threshold: float, method: str = "", alone: float | None = None,
                             top: int = 10, images: str = "the val split") -> str:
    """The chosen point, the ``top`` best points of the search and the ``CRITERION`` with every detection kept."""
    def point_cells(p: OperatingPoint) -> str:
        return " | ".join([f"{t:.2f}" for t in p.thresholds] + [f"{s:g}" for s in p.min_sides])

    head = " | ".join([f"{c} score ≥" for c in classes] + [f"{c} side ≥ (px)" for c in classes])
    ranked = sorted(seen.items(), key=lambda kv: (-kv[1], sum(kv[0].thresholds), kv[0].thresholds,
                                                  sum(kv[0].min_sides), kv[0].min_sides))
    lines = ["# Operating point", "",
             f"Chosen on {images} by the end-to-end {CRITERION}{' of `' + method + '`' if method else ''}, over "
             f"{len(seen)} points; among equals the one that keeps the most. `operating_point.png` shows the "
             "cuts through it.", "",
             f"| | {head} | {CRITERION} |", "|---" * (2 * len(classes) + 2) + "|",
             f"| **chosen** | {point_cells(chosen)} | **{seen[chosen]:.2f}** |"]
    if alone is not None:
        lines.append(f"| the relation model alone, same point | {point_cells(chosen)} | {alone:.2f} |")
    lines.append(f"| every detection kept | {' | '.join(['–'] * (2 * len(classes)))} | {at_score_threshold:.2f} |")
    lines += ["", f"The {min(top, len(ranked))} best points:", "", f"| rank | {head} | {CRITERION} |",
              "|---" * (2 * len(classes) + 2) + "|"]
    lines += [f"| {i} | {point_cells(p)} | {f1:.2f} |" for i, (p, f1) in enumerate(ranked[:top], 1)]
    return "\n".join(lines) + "\n"


def write_operating_point_report(directory: str | Path, seen: Mapping[OperatingPoint, float], chosen: OperatingPoint,
                                 classes: Sequence[str], at_score_threshold: float, method: str = "",
                                 alone: float | None = None, images: str = "the val split") -> None:
    """``operating_point.md`` in ``directory``, and ``operating_point.png`` where there are two classes to plot."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "operating_point.md").write_text(operating_point_markdown(
        seen, chosen, classes, at_score_threshold, method, alone, images=images))
    if len(classes) == 2:
        plot_operating_point(seen, chosen, classes, directory / "operating_point.png", method, images)
