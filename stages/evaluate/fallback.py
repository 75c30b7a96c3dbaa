"""One relation method's claims, and a second method's for the wheels the first leaves without an owner.

DeepWORD leaves a wheel unclaimed when no vehicle scores high enough for it; on detected boxes that is often a
true pair whose vehicle box stops short of the wheel, which the paper's IoU rule still claims. ``deepword_then_logic``
(stages/evaluate/methods.py, ``deepword infer --method``) keeps every DeepWORD claim and couple as it is and adds the
IoU rule's claim for each wheel DeepWORD left alone (docs/detector.md, "The IoU rule for the wheels DeepWORD leaves
unclaimed").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from stages.word_format import Record

# name -> (primary method, fallback method): the report's rows (stages/evaluate/methods.py) and `deepword infer
# --method` (stages/inference/infer.py) both build these from their own registries
FALLBACKS = {"deepword_then_logic": ("deepword", "logic")}


@dataclass
class ClaimFallback:
    """``primary``'s relations and couples, plus ``fallback``'s relations of the wheels ``primary`` claims for no
    vehicle. Both methods see the same boxes; a wheel never gets a second owner."""

    primary: object     # predict(record) -> Record
    fallback: object
    name: str

    def predict(self, rec: Record) -> Record:
        first = self.primary.predict(rec)
        claimed = {int(w) for _, w, _ in first.relations}
        added = [rel for rel in self.fallback.predict(rec).relations if int(rel[1]) not in claimed]
        return replace(first, relations=[*first.relations, *added])
