"""Problems found in an annotation tool's export: every one is collected (not just the first), each as one
line naming the file, the element (task, annotation, region, box, image) and the field."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

DEFAULT_LIMIT = 50  # problems printed; the rest are counted


@dataclass
class Problem:
    file: str
    where: str
    field: str
    message: str

    def __str__(self) -> str:
        where = f" {self.where}:" if self.where else ""
        return f"{self.file}:{where} field '{self.field}': {self.message}"


@dataclass
class Problems:
    """The problems of one input file, in the order they were found."""

    file: str
    items: list[Problem] = field(default_factory=list)

    def add(self, where: str, fld: str, message: str) -> None:
        self.items.append(Problem(os.path.basename(self.file) or self.file, where, fld, message))

    def __bool__(self) -> bool:
        return bool(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def lines(self, limit: int = DEFAULT_LIMIT) -> list[str]:
        out = [str(p) for p in self.items[:limit]]
        if len(self.items) > limit:
            out.append(f"... and {len(self.items) - limit} more problems")
        return out


class LabellingError(ValueError):
    """An import or export that cannot go ahead; ``problems`` holds every problem found (one line each)."""

    def __init__(self, problems: Problems | list[str] | str):
        if isinstance(problems, str):
            self.all_lines = [problems]
        elif isinstance(problems, Problems):
            self.all_lines = [str(p) for p in problems.items]
        else:
            self.all_lines = list(problems)
        self.count = len(self.all_lines)
        super().__init__("\n".join(self.lines()))

    def lines(self, limit: int = DEFAULT_LIMIT) -> list[str]:
        """The problems, one a line, at most ``limit`` of them and a count of the rest."""
        out = self.all_lines[:limit]
        if self.count > limit:
            out.append(f"... and {self.count - limit} more problems")
        return out
