"""One relation method's claims, and a second method's for the wheels the first leaves without an owner.

DeepWORD leaves a wheel unclaimed when no vehicle scores high enough for it; on detected boxes that is often a
true pair whose vehicle box stops short of the wheel, which the paper's IoU rule still claims. ``deepword_then_logic``
keeps every DeepWORD claim and couple as it is and adds the IoU rule's claim for each wheel DeepWORD left alone
(docs/detector.md, "The IoU rule for the wheels DeepWORD leaves unclaimed"). It is the bundle's end-to-end method
(``export.end_to_end``): the export stage fits the rule on train, stores it in ``export.json`` and chooses the
detector's operating point by this method's pair_f1; the evaluate stage's row and ``deepword infer`` run it from
there (``deepword.inference.runtime.bundle_method``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

from deepword.word_format import Record

# name -> (primary method, fallback method): the report's rows (stages/evaluate/methods.py), the bundle's end-to-end
# method and `deepword infer --method` (deepword/inference/runtime.py) build these from their own registries
FALLBACKS = {"deepword_then_logic": ("deepword", "logic")}


def claim_unclaimed(first: Record, second: Record) -> Record:
    """``first`` with ``second``'s relations of the wheels ``first`` claims for no vehicle added after its own (both
    predictions of the same boxes); a wheel never gets a second owner, couples stay ``first``'s."""
    claimed = {int(w) for _, w, _ in first.relations}
    added = [rel for rel in second.relations if int(rel[1]) not in claimed]
    return replace(first, relations=[*first.relations, *added])


@dataclass
class ClaimFallback:
    """``primary``'s relations and couples, plus ``fallback``'s relations of the wheels ``primary`` claims for no
    vehicle (``claim_unclaimed``)."""

    primary: object     # predict(record) -> Record
    fallback: object
    name: str

    def predict(self, rec: Record) -> Record:
        return claim_unclaimed(self.primary.predict(rec), self.fallback.predict(rec))


def batch_with_fallback(predict: Callable[[list[Record]], list[Record]],
                        fallback) -> Callable[[list[Record]], list[Record]]:
    """A batch predictor (``records -> records``, as the operating-point search calls one) whose every prediction
    has ``fallback``'s claims added for the wheels ``predict`` leaves unclaimed."""

    def combined(records: Sequence[Record]) -> list[Record]:
        return [claim_unclaimed(p, fallback.predict(r)) for p, r in zip(predict(list(records)), records, strict=True)]

    return combined
