"""``relation.distill``: the relation ensemble distilled into one network that ships in its place (docs/domain.md,
"One network taught by the three"). The training is ``student``'s; this module holds what the stage reads without
torch."""

from __future__ import annotations

from dataclasses import dataclass

STUDENT = "student"   # the student's place among the members (its directory members/student, its progress label)
STARTS = ("scratch", "member")


@dataclass(frozen=True)
class DistillConfig:
    """``relation.distill``: whether the members are distilled into one shipped network, and the loss weights."""
    enabled: bool = False
    weight: float = 1.0        # the teachers' term beside the labels' (weight 1 of the training's own loss)
    label_weight: float = 1.0  # the labels' loss (relation.loss's); 0: the teachers alone
    start: str = "scratch"     # scratch: its own initial weights (seed after the members'); member: the first member's

    @classmethod
    def from_cfg(cls, node) -> DistillConfig:
        if node is None:
            return cls()
        cfg = cls(enabled=bool(node.get("enabled", False)), weight=float(node.get("weight", 1.0)),
                  label_weight=float(node.get("label_weight", 1.0)), start=str(node.get("start", "scratch")))
        if cfg.weight < 0 or cfg.label_weight < 0 or cfg.weight + cfg.label_weight == 0:
            raise ValueError(f"relation.distill: weight ({cfg.weight}) and label_weight ({cfg.label_weight}) must be "
                             ">= 0 and not both 0")
        if cfg.start not in STARTS:
            raise ValueError(f"relation.distill.start must be one of {STARTS}, got {cfg.start!r}")
        return cfg

    def ships_student(self, members: int) -> bool:
        """Whether the relation stage ships a student rather than its ``members`` networks (one has nothing to teach)."""
        return self.enabled and members > 1

