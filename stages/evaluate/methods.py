"""The report's rows (methods) and box sources, as registries the evaluate stage iterates over.

A method factory takes the EvalContext and returns an object with ``name`` and
``predict(record) -> Record`` (same boxes, predicted relations and couples), or None when an upstream
stage it needs is not among the evaluate stage's inputs (the row is then reported as skipped).
A box source returns ``{image: Record}`` for the test split holding only boxes (relations cleared), or
None when unavailable. Adding a row is one factory in ``METHODS``, its upstream stage in the evaluate stage's ``inputs``
(conf/config.yaml) and its name in ``eval.methods``; ``deepword_onnx`` below is the example. A box
source is one function in ``BOX_SOURCES``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from deepword.inference.runtime import NoDetectorError, OnnxDetector, bundle_rule, deepword_method
from deepword.rules.baselines import (
    RULES,
    CoupleRule,
    SearchGrids,
    TrainImage,
    fit_couple_rule,
    fit_logic,
    fit_logic_plus,
    fit_prior,
    prepare_train,
)
from deepword.rules.fallback import FALLBACKS, ClaimFallback
from deepword.word_format import Dataset, Record, boxes_only, load_image, read_records
from pipeline.outputs import StageInputs


class LastImage:
    """``load_rgb(record)`` keeping the last decoded image, read-only (an in-place change by one row would reach the
    next one's input): the evaluate stage runs every row on one image before the next (``score_dataset``)."""

    def __init__(self, root: str | Path):
        self.root, self.last = root, None   # (image, rgb)

    def __call__(self, rec: Record) -> np.ndarray:
        if self.last is None or self.last[0] != rec.image:
            rgb = load_image(self.root, rec)
            rgb.flags.writeable = False
            self.last = (rec.image, rgb)
        return self.last[1]


@dataclass
class Remembered:
    """A row that keeps its last prediction (records are never changed once predicted): the evaluate stage runs
    every row on one image before the next, so a row building on this one gets its prediction of the same boxes."""

    method: object      # predict(record) -> Record
    name: str
    last: tuple | None = field(default=None, repr=False)   # ((image, boxes bytes), prediction)

    def predict(self, rec: Record) -> Record:
        key = (rec.image, rec.boxes.tobytes())
        if self.last is None or self.last[0] != key:
            self.last = (key, self.method.predict(rec))
        return self.last[1]


@dataclass
class EvalContext:
    """What method factories and box sources may use: the evaluate config, inputs, the dataset scored, the
    dataset whose train split the baselines are fitted on (``fit_dataset``, default: the scored one; the
    held-out domain is scored with baselines fitted in-domain) and priors."""

    cfg: object            # the `eval` config subtree
    seed: int
    inputs: StageInputs    # the stage's inputs, with their declared outputs (pipeline.outputs)
    dataset: Dataset
    priors: object         # deepword.priors.Priors
    notes: list[str] = field(default_factory=list)
    fit_dataset: Dataset | None = None
    _shared: dict = field(default_factory=dict, repr=False)

    def shared(self, name: str, build: Callable[[], object]) -> Remembered:
        """The one instance of row ``name`` in this context, built by ``build`` on first use: the rows that add to
        another row's predictions (``deepword_then_logic`` on ``deepword``) reuse them instead of running the model
        again on the same boxes."""
        if name not in self._shared:
            self._shared[name] = Remembered(build(), name)
        return self._shared[name]

    @cached_property
    def load_rgb(self) -> LastImage:
        """The scored dataset's images, the last one decoded kept: ``deepword`` and ``deepword_int8`` decode each
        image once between them."""
        return LastImage(self.dataset.root)

    @cached_property
    def train(self) -> list[TrainImage]:
        fit = self.fit_dataset or self.dataset
        return prepare_train(fit.subset("train"), float(self.cfg.min_box_px), int(self.cfg.fit_images), self.seed)

    @cached_property
    def exported_detections(self) -> tuple[object, dict[str, Record]] | None:
        """(the export stage's ``OnnxDetector``, {image: every detection of the test split down to its
        score_threshold}), or None without an exported detector. One pass serves the relation rows (at the
        operating point, ``detected_boxes``) and the AP (every score, ``detections_for_ap``)."""
        if "export" not in self.inputs:
            return None

        try:
            detector = OnnxDetector(self.inputs["export"], threads=int(self.cfg.get("threads", 1)))
        except NoDetectorError:
            return None
        return detector, {r.image: detector.detect_every(load_image(self.dataset.root, r), r)
                          for r in self.dataset.subset("test")}

    @cached_property
    def grids(self) -> SearchGrids:
        return SearchGrids.from_cfg(self.cfg.baseline_grids)

    @cached_property
    def couple_rule(self) -> CoupleRule:
        return fit_couple_rule(self.train, self.grids.couple_tolerance)


def deepword_onnx(name: str) -> Callable[[EvalContext], object | None]:
    """The ``deepword`` (FP32) and ``deepword_int8`` rows: the exported relation model in onnxruntime, the
    model that ships (``deepword.inference.runtime``); needs the export stage's output."""

    def factory(ctx: EvalContext):
        if "export" not in ctx.inputs:
            return None

        return ctx.shared(name, lambda: deepword_method(name, ctx.inputs["export"], ctx.dataset.root,
                                                        load_rgb=ctx.load_rgb))

    return factory


def claim_fallback(name: str) -> Callable[[EvalContext], object | None]:
    """A ``FALLBACKS`` row (deepword/rules/fallback.py): its primary method's claims, and its fallback's for the
    wheels the primary leaves unclaimed, as the bundle ships them (the fallback rule fitted on train by the export
    stage, the same fit as this stage's own row of that rule), so that the row is what ``deepword infer`` does."""

    def factory(ctx: EvalContext):
        if "export" not in ctx.inputs:
            return None

        primary, fallback = FALLBACKS[name]
        # the primary row's own instance: on boxes it has already predicted, its relations are reused
        return ClaimFallback(METHODS[primary](ctx), bundle_rule(ctx.inputs["export"], fallback), name)

    return factory


# rows fitted on the train sample alone (EvalContext.train), the rule methods (deepword.rules.baselines.RULES): the
# held-out domain's rows reuse the in-domain fits
FITTED_ON_TRAIN = tuple(RULES)

METHODS: dict[str, Callable[[EvalContext], object | None]] = {
    "logic": lambda ctx: fit_logic(ctx.train, ctx.couple_rule, ctx.grids.logic_iou),
    "logic_plus": lambda ctx: fit_logic_plus(ctx.train, ctx.couple_rule, ctx.grids.logic_plus,
                                             ctx.grids.logic_plus_rounds),
    "prior": lambda ctx: fit_prior(ctx.train, ctx.priors, ctx.grids.prior_owner, ctx.grids.prior_couple),
    "deepword": deepword_onnx("deepword"),
    "deepword_int8": deepword_onnx("deepword_int8"),
}
METHODS |= {name: claim_fallback(name) for name in FALLBACKS}


def gt_boxes(ctx: EvalContext) -> dict[str, Record]:
    return {r.image: boxes_only(r) for r in ctx.dataset.subset("test")}


def detected_boxes(ctx: EvalContext) -> dict[str, Record] | None:
    """Detections of the test split: from the exported detector in onnxruntime when the export stage is
    an input (the pipeline's DAG: what ships), at its operating point; else the detector stage's
    test predictions (its declared output ``predictions``, of the in-domain dataset only); None when the run has no
    detector."""
    if "export" in ctx.inputs:
        if ctx.exported_detections is None:
            return None
        detector, every = ctx.exported_detections
        return {image: detector.keep_operating_point(rec) for image, rec in every.items()}
    if "detector" not in ctx.inputs or ctx.fit_dataset is not None:
        return None
    path = ctx.inputs.output("detector", "predictions", split="test")
    records = read_records(path, root=ctx.dataset.root, allow_empty=True)
    return {r.image: boxes_only(r) for r in records}


def footprint_detections(ctx: EvalContext) -> dict[str, Record] | None:
    """The test split's detections the footprints are made from (the bundle's footprint point:
    ``OnnxDetector.keep_footprint_point``, which keeps the operating point's boxes under the same ids and adds the
    vehicles only it keeps); None without an exported detector."""
    if ctx.exported_detections is None:
        return None
    detector, every = ctx.exported_detections
    return {image: detector.keep_footprint_point(rec) for image, rec in every.items()}


def detections_for_ap(ctx: EvalContext) -> list[Record] | None:
    """Every detection of the test split down to the detector's ``score_threshold`` (the exported detector,
    without its operating point): the detector stage's AP protocol. Average precision sweeps the score, so
    detections cut at the operating point would end the precision-recall curve there and understate it.
    None when the run has no exported detector."""
    return None if ctx.exported_detections is None else list(ctx.exported_detections[1].values())


BOX_SOURCES: dict[str, Callable[[EvalContext], dict[str, Record] | None]] = {
    "gt": gt_boxes,
    "detected": detected_boxes,
}
