"""Tables of measured values, written as Markdown and CSV, and the figure writing that goes with them.
Cells are strings, floats (two decimals) or None (shown as ``n/a``, left empty in CSV)."""

from __future__ import annotations

import csv
import re
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


def _cell(text: str):
    if text == NOT_AVAILABLE:
        return None
    if re.fullmatch(r"-?\d+", text):
        return int(text)
    if re.fullmatch(r"-?\d+\.\d+", text):
        return float(text)
    return text


def between(text: str, begin: str, end: str) -> str | None:
    """The text between the markers ``begin`` and ``end`` of a page, or None where either is missing."""
    if begin not in text or end not in text:
        return None
    return text.split(begin, 1)[1].split(end, 1)[0]


def tables_in_markdown(text: str) -> dict[str, Table]:
    """Every table of a page that ``Table.markdown`` wrote (a heading, then a pipe table), by title."""
    found = {}
    blocks = re.split(r"^(?=#+ )", text, flags=re.MULTILINE)
    for block in blocks:
        if block.startswith("#") and "\n|" in block:
            table = Table.from_markdown(block)
            found[table.title] = table
    return found


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

    @classmethod
    def from_markdown(cls, block: str) -> Table:
        """The table ``markdown`` wrote, read back: its title, header, rows and notes. Cells read as ``fmt`` wrote
        them: ``n/a`` as None, whole numbers as int, numbers with decimals as float, anything else (and every
        row's first cell, its label) as the string."""
        lines = block.strip("\n").split("\n")
        title = lines[0].lstrip("#").strip()
        table = [line for line in lines[1:] if line.startswith("|")]
        notes = [line[2:] for line in lines[1:] if line.startswith("- ")]
        split = [[c.strip() for c in line.strip()[1:-1].split(" | ")] for line in table]
        rows = [[row[0], *map(_cell, row[1:])] for row in split[2:]]
        return cls(title, split[0] if split else [], rows, notes)

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
