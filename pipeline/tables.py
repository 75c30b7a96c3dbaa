"""Tables of measured values, written as Markdown and CSV, and the figure writing that goes with them.
Cells are strings, floats (two decimals) or None (shown as ``n/a``, left empty in CSV)."""

from __future__ import annotations

import csv
import statistics
from dataclasses import dataclass
from pathlib import Path

NOT_AVAILABLE = "n/a"


def fmt(value) -> str:
    if value is None:
        return NOT_AVAILABLE
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


@dataclass
class Table:
    title: str
    header: list[str]
    rows: list[list]          # cells: str, float or None (shown as n/a)
    notes: list[str]

    def markdown(self, level: int = 2) -> str:
        lines = [f"{'#' * level} {self.title}", "", "| " + " | ".join(self.header) + " |",
                 "|" + "|".join("---" for _ in self.header) + "|"]
        lines += ["| " + " | ".join(fmt(c) for c in row) + " |" for row in self.rows]
        return "\n".join(lines + [""] + [f"- {n}" for n in self.notes] + [""])

    def write_csv(self, path: Path) -> None:
        with path.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(self.header)
            writer.writerows([["" if c is None else c for c in row] for row in self.rows])


def paired_difference(diffs: list[float]) -> str:
    """Mean of paired differences with its standard error (sample sd / sqrt(n)), e.g. "-0.02 ± 0.18"; the
    mean alone for one pair."""
    if not diffs:
        return NOT_AVAILABLE
    mean = statistics.fmean(diffs)
    if len(diffs) == 1:
        return f"{mean:+.2f}"
    return f"{mean:+.2f} ± {statistics.stdev(diffs) / len(diffs) ** 0.5:.2f}"


def save_figure(fig, path: Path, rect: tuple[float, float, float, float] = (0, 0, 1, 1)) -> None:
    """Lay out (the axes within ``rect`` of the figure: room for a legend beside them), write as PNG (creating the
    folder) and close a matplotlib figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout(rect=rect)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
