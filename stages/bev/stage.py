"""The ``bev`` stage: vehicle footprints in bird's-eye view from wheel contacts, per relation method, on the
box sources the evaluate stage scored, fused over each frame's cameras and scored against ``objects_3d``.

It reads the relations evaluate predicted (``predictions/<boxes>_<method>.jsonl``: the shipped ONNX models
and the fitted baselines, exactly as evaluate scores them) and adds ``box_bottom`` (no relation). Needs
``calibration`` and ``objects_3d`` in the dataset (docs/design.md §4): a dataset without any is reported as such
(no metrics); a dataset where some records lack them is an error naming the first one's file and line.

Outputs: ``bev.json`` (every number), ``bev_report.md``, ``footprint_prior.json`` (the shape prior fitted on
train), ``footprints/<boxes>_<method>.jsonl`` (fused footprints per frame) and ``artifacts/top_view_*.png``.
MLflow keys (docs/design.md §7): the detection scores (``stages.bev.metrics.detection_scores``: nuScenes AP at
0.5/1/2/4 m, ATE, ASE, AOE, IoU, recall, precision) as ``bev.<boxes>.<method>.<subset>.<metric>`` for the subsets
``all``, ``two_wheels``, ``one_wheel``, ``no_wheel`` (within ``bev.max_range_m``) and the ``<lo>-<hi>m`` distance
bins; where the boxes carry facing vectors (the bundle's facing network, which the stage runs on every vehicle box:
``deepword.inference.facing_net.OnnxFacing``; else a detector's facing head) ``bev.<boxes>.facing.{acc,vehicles}``
(``metrics.facing_agreement``: how often they point the right way on the matched test vehicles) and
``bev.<boxes>.facing.{camera_pairs,camera_agreement,implied_acc,trust}`` (the same without labels:
``deepword.footprint.camera_agreement``, and the weight the votes were given for it: ``facing_trust``); and the paired
medians as ``bev.<boxes>.<method>.<metric>``
(matched vehicles within ``bev.max_range_m``),
``bev.<boxes>.<method>.<population>.<metric>`` for the populations ``paired`` (two same-side wheels
visible) and ``hard`` (in a hard test image) within the range, and ``<lo>_<hi>m`` distance bins.

With the held-out domain among its inputs (``shift_data``: evaluate scored it too, its predictions under
``shift/predictions/``) the same keys under ``bev.shift.`` (``bev.shift.<boxes>.<method>.<subset>.<metric>``),
footprints under ``shift/footprints/`` and figures ``artifacts/shift_top_view_*.png``; the held-out domain has no
train split, so its footprints use the prior fitted on the in-domain train split.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from deepword.footprint import (
    FootprintPrior,
    camera_agreement,
    fit_prior,
    group_confidence,
    group_wheels,
    implied_accuracy,
    wheel_contacts,
    write_footprints,
)
from deepword.format_3d import Missing3DError, has_3d_truth, record_camera, record_objects_3d
from deepword.inference.facing_net import OnnxFacing
from deepword.top_view import fused_top_view, panel_grid, top_view
from deepword.word_format import WHEEL, Dataset, Record, load_image, open_dataset, read_records
from pipeline.outputs import StageInputs
from stages.bev.fitting import facing_lead, frame_views, fused_footprints
from stages.bev.metrics import (
    DETECTION_METRICS,
    METRICS,
    Scored,
    TrueVehicle,
    detection_scores,
    facing_agreement,
    match_frame,
    role_agreement,
    summarise,
)

NEEDED_BY = "the bev stage"
BASELINE = "box_bottom"
PRIOR_FILE = "footprint_prior.json"


def check_3d(records: list[Record]) -> bool:
    """True when every record has calibration and objects_3d, False when none has; a mix is an error
    naming the first record without them."""
    have = [has_3d_truth(r) for r in records]
    if not any(have):
        return False
    for rec, ok in zip(records, have, strict=True):
        if not ok:
            record_camera(rec, NEEDED_BY)
            record_objects_3d(rec, NEEDED_BY)
    return True


def train_prior(ds: Dataset, fit_images: int, seed: int) -> FootprintPrior:
    train = ds.subset("train")
    if len(train) > fit_images:
        train = random.Random(seed).sample(train, fit_images)
    return fit_prior((rec, record_camera(rec, NEEDED_BY), *record_objects_3d(rec, NEEDED_BY)) for rec in train)


def frame_truth(test: list[Record], hard: set[str]) -> dict[int, list[TrueVehicle]]:
    """True vehicles per frame, one per physical vehicle (the same 3D box seen by several cameras)."""
    frames: dict[int, dict[tuple, TrueVehicle]] = defaultdict(dict)
    for rec in test:
        vehicles, _ = record_objects_3d(rec, NEEDED_BY)
        owner = rec.owner_of()
        paired = {owner[a] for a, b in rec.wheel_pairs if a in owner and owner.get(b) == owner[a]}
        n_wheels = defaultdict(int)
        for v in owner.values():
            n_wheels[v] += 1
        for vid, box in vehicles.items():
            key = (round(box.x, 2), round(box.y, 2))
            tv = frames[rec.frame_id].setdefault(key, TrueVehicle(box))
            tv.paired |= vid in paired
            tv.hard |= rec.image in hard
            tv.wheels = max(tv.wheels, min(2, n_wheels[vid]))
    return {f: list(v.values()) for f, v in frames.items()}


def populations(bcfg) -> dict[str, callable]:
    """Name -> predicate on a TrueVehicle; '' is every vehicle within the range (the headline keys)."""
    rng = float(bcfg.max_range_m)
    pops = {"": lambda t: t.range_m <= rng, "paired": lambda t: t.range_m <= rng and t.paired,
            "hard": lambda t: t.range_m <= rng and t.hard}
    for lo, hi in bcfg.range_bins:
        pops[f"{lo:g}_{hi:g}m"] = lambda t, lo=float(lo), hi=float(hi): lo <= t.range_m < hi
    return pops


WHEEL_POPULATIONS = {"two_wheels": 2, "one_wheel": 1, "no_wheel": 0}


def _in_bin(lo: float, hi: float):
    return lambda x: lo <= x.range_m < hi


def detection_subsets(bcfg) -> dict[str, tuple]:
    """Subset name -> (true-vehicle predicate, estimate predicate for false positives) of the detection scores:
    ``all`` within ``bev.max_range_m``; the wheel populations within it (a true vehicle by its wheels annotated in
    one of its images; an unmatched estimate within the range is a false positive of every population, as Waymo
    counts its difficulty levels: an estimate cannot choose its population by the evidence it claims); the
    distance bins ``<lo>-<hi>m`` (true vehicles and estimates each by its own range)."""
    rng = float(bcfg.max_range_m)
    in_range = lambda x: x.range_m <= rng  # noqa: E731
    subsets = {"all": (in_range, in_range)}
    for name, k in WHEEL_POPULATIONS.items():
        subsets[name] = (lambda t, k=k: t.range_m <= rng and t.wheels == k, in_range)
    for lo, hi in bcfg.range_bins:
        inside = _in_bin(float(lo), float(hi))
        subsets[f"{lo:g}-{hi:g}m"] = (inside, inside)
    return subsets


def scored(fused_frame: list) -> list[Scored]:
    return [Scored(box, group_confidence(g), group_wheels(g)) for box, g in fused_frame]


def run(cfg, inputs: StageInputs, out_dir: Path) -> dict[str, float]:
    bcfg, seed = cfg.bev, int(cfg.seed)
    out_dir = Path(out_dir)
    artifacts = out_dir / "artifacts"
    artifacts.mkdir(parents=True, exist_ok=True)
    ds = open_dataset(inputs["data"])
    if not check_3d(ds.records):
        first = ds.records[0]
        file, line = first.source or (first.image, None)
        note = (f"no BEV results: the dataset has no `calibration` / `objects_3d` keys (e.g. {file}:{line}); "
                "the bev stage needs both (docs/design.md §4, docs/bev.md)")
        print(f"bev: {note}")
        (out_dir / "bev_report.md").write_text(f"# Bird's-eye view\n\n{note}\n")
        shutil.copy(out_dir / "bev_report.md", artifacts / "bev_report.md")
        return {}
    # the prior as shipped (rounded in footprint_prior.json): what deepword infer reads, so both give one footprint
    prior = FootprintPrior.from_json(train_prior(ds, int(bcfg.fit_images), seed).to_json())
    (out_dir / PRIOR_FILE).write_text(json.dumps(prior.to_json(), indent=1))
    e2e = end_to_end_method(inputs.output("evaluate", "report"))
    facing_net = OnnxFacing.from_bundle(inputs["export"]) if "export" in inputs else None
    domain = score_domain(ds, "", inputs, prior, bcfg, out_dir, facing_net, e2e)
    report = {**domain.report, "prior": prior.to_json(), "max_range_m": float(bcfg.max_range_m),
              "match_m": float(bcfg.match_m), "fuse_radius_m": float(bcfg.fuse_radius_m)}
    metrics = domain.metrics("bev")
    figures = write_figures(artifacts, domain.test, domain.truth, domain.cameras, domain.fused_by, prior, bcfg, e2e)
    if "shift_data" in inputs:   # the held-out domain: evaluate's predictions there, the same prior (fitted in domain)
        heldout = open_dataset(inputs["shift_data"])
        if check_3d(heldout.records):
            shift = score_domain(heldout, HELDOUT_PREFIX, inputs, prior, bcfg, out_dir, facing_net, e2e)
            report["shift"] = shift.report
            metrics |= shift.metrics("bev.shift")
            figures += write_figures(artifacts, shift.test, shift.truth, shift.cameras, shift.fused_by, prior, bcfg,
                                     e2e, prefix="shift_")
        else:
            report["notes"].append("held-out domain: no `calibration` / `objects_3d` keys, no held-out rows")
    (out_dir / "bev.json").write_text(json.dumps(report, indent=1))
    (out_dir / "bev_report.md").write_text(render_report(report, bcfg))
    for name in ("bev_report.md", "bev.json", PRIOR_FILE):
        shutil.copy(out_dir / name, artifacts / name)
    print(f"bev: {len(figures)} top-view figures (artifacts/top_view_*.png, artifacts/shift_top_view_*.png)")
    return metrics


HELDOUT_PREFIX = "shift/"   # evaluate's held-out predictions (its `domain_predictions` output) and bev's own


@dataclass
class Domain:
    """One dataset's test split scored: the paired medians and detection scores per box source and method, the
    fused footprints per (boxes, method) and frame, and what the figures need."""

    test: list
    truth: dict
    cameras: dict
    results: dict
    detection: dict
    fused_by: dict
    notes: list
    facing: dict      # {boxes: facing_agreement} for the box sources whose detections carry the facing head's vectors
    roles: dict       # {boxes: role_agreement} of the method deepword infer runs on those boxes

    @property
    def report(self) -> dict:
        return {"results": self.results, "detection": self.detection, "notes": self.notes, "frames": len(self.truth),
                "facing": self.facing, "roles": self.roles}

    def metrics(self, root: str) -> dict[str, float]:
        """``flatten``'s keys, ``<root>.<boxes>.facing.<key>`` (``facing_agreement``'s and the cameras' agreement) and
        ``<root>.<boxes>.roles.<key>`` (``role_agreement``'s)."""
        out = flatten(self.results, self.detection, root)
        for part, scores in (("facing", self.facing), ("roles", self.roles)):
            for boxes, score in scores.items():
                out |= {f"{root}.{boxes}.{part}.{k}": float(v) for k, v in score.items() if not isinstance(v, str)}
        return out


def score_domain(ds: Dataset, prefix: str, inputs: StageInputs, prior: FootprintPrior, bcfg, out_dir: Path,
                 facing_net=None, end_to_end: str = "deepword") -> Domain:
    """Footprints of every method evaluate predicted on ``ds``'s test split (``prefix`` "" in domain, ``shift/`` the
    held-out domain: evaluate's ``<prefix>predictions/`` in, the stage's ``<prefix>footprints/`` out), scored; with
    ``facing_net`` (the bundle's ``OnnxFacing``) every vehicle box carries its facing vector."""
    test = ds.subset("test")
    cameras = {r.image: record_camera(r, NEEDED_BY) for r in test}
    truth = frame_truth(test, set(ds.splits.get("hard", [])))
    pops = populations(bcfg)
    results, detection, notes, facing, roles = {}, {}, [], {}, {}
    (out_dir / prefix / "footprints").mkdir(parents=True, exist_ok=True)
    reads = {}   # {boxes: {method: {image: record}}}: the predictions the footprints are made from
    relations = {}   # {boxes: {method: path}}: the predictions evaluate scored, where the footprints' differ
    for boxes in bcfg.box_sources:
        predictions = {m: inputs.output("evaluate", "domain_predictions", domain=prefix, boxes=boxes, method=m)
                       for m in bcfg.methods}
        methods = [m for m in bcfg.methods if predictions[m].is_file()]
        for m in bcfg.methods:
            if m not in methods:
                notes.append(f"`{boxes}` / `{m}` skipped: evaluate wrote no {prefix}predictions/{predictions[m].name}")
        if methods:
            sources = {m: footprint_source(inputs, prefix, boxes, m, predictions[m]) for m in methods}
            reads[boxes] = {m: {r.image: r for r in read_records(sources[m], root=ds.root, allow_empty=True)}
                            for m in methods}
            relations[boxes] = {m: predictions[m] for m in methods if sources[m] != predictions[m]}
    if facing_net is not None:   # the facing network's vectors replace any a detector wrote
        reads = with_facing_vectors(reads, facing_net, ds.root)
    jobs = {}   # {(boxes, method): (views by frame, use_relations)}
    for boxes, read in reads.items():
        first = next(iter(read))   # box_bottom reads the methods' shared boxes, without relations
        for method in [BASELINE, *read]:
            jobs[(boxes, method)] = (frame_views(read[first if method == BASELINE else method], test, cameras),
                                     method != BASELINE)
    # the facing network's votes weighed by how far its cameras agree on these frames (deepword.footprint.facing_trust)
    fused_by, trust = fused_footprints(jobs, list({r.frame_id for r in test}), prior, float(bcfg.fuse_radius_m),
                                       int(bcfg.workers or os.cpu_count() or 1),
                                       facing_val_accuracy=facing_net.accuracy if facing_net is not None else None,
                                       desc=f"bev: footprints{' (held-out domain)' if prefix else ''}")
    for boxes, read in reads.items():
        methods = list(read)
        results[boxes] = {}
        agreement = facing_agreement(test, read[methods[0]])   # the methods share their boxes
        if agreement is not None:
            # and the label-free check a new camera's frames allow: do two cameras' votes on one vehicle agree?
            voted = fused_by[facing_lead(boxes, methods)]
            pairs, agreeing = camera_agreement([g for f in voted.values() for g in f])
            implied = implied_accuracy(pairs, agreeing)
            facing[boxes] = {**agreement, "camera_pairs": float(pairs),
                             **({} if implied is None else {"camera_agreement": 100.0 * agreeing / pairs,
                                                            "implied_acc": 100.0 * implied}),
                             **({"trust": trust[boxes]} if boxes in trust else {})}
        # the roles deepword infer writes, for the method it runs on these boxes by default
        infer_method = end_to_end if boxes == "detected" and end_to_end in read else facing_lead(boxes, methods)[1]
        named = read[infer_method]   # infer writes the roles onto the relations at the operating point
        if infer_method in relations[boxes]:
            named = {r.image: r for r in read_records(relations[boxes][infer_method], root=ds.root, allow_empty=True)}
            if facing_net is not None:   # their boxes are the footprint point's under the same ids: copy the vectors
                named = {image: facing_net.with_vectors_of(r, read[infer_method][image])
                         if image in read[infer_method] else r for image, r in named.items()}
        agreement = role_agreement(test, named, fused_by[(boxes, infer_method)], cameras, prior)
        if agreement is not None:
            roles[boxes] = {**agreement, "method": infer_method}
        for method in [BASELINE, *methods]:
            fused = fused_by[(boxes, method)]
            matches = {f: match_frame(truth.get(f, []), [b for b, _ in fused[f]], float(bcfg.match_m)) for f in fused}
            results[boxes][method] = {
                pop: summarise([m for ms in matches.values() for m in ms if keep(m.truth)]) for pop, keep in pops.items()}
            frames = [(truth.get(f, []), scored(fused[f])) for f in sorted(fused)]
            detection.setdefault(boxes, {})[method] = {
                name: detection_scores(frames, *keep) for name, keep in detection_subsets(bcfg).items()}
            write_footprints(out_dir / prefix / "footprints" / f"{boxes}_{method}.jsonl", fused)
    return Domain(test, truth, cameras, results, detection, fused_by, notes, facing, roles)


def footprint_source(inputs: StageInputs, prefix: str, boxes: str, method: str, scored: Path) -> Path:
    """The predictions a method's footprints are made from: on detected boxes, evaluate's on the detections of the
    bundle's footprint point (box name ``footprints``: vehicles down to a lower score than the operating point's,
    docs/bev.md, "Which detections the footprints take"), where it wrote them; else those it scored (``scored``)."""
    if boxes == "detected":
        path = inputs.output("evaluate", "domain_predictions", domain=prefix, boxes="footprints", method=method)
        if path.is_file():
            return path
    return scored


def with_facing_vectors(reads: dict, facing_net, root) -> dict:
    """Every box source's predictions ({boxes: {method: {image: record}}}) with the facing network's vector of each
    vehicle box (``OnnxFacing.with_vectors``): each image decoded once, its vectors computed once per set of boxes
    (the methods of one source share their boxes; labelled and detected boxes differ)."""
    out = {boxes: {method: {} for method in read} for boxes, read in reads.items()}
    for image in sorted({image for read in reads.values() for records in read.values() for image in records}):
        rgb, vectors = None, {}
        for boxes, read in reads.items():
            for method, records in read.items():
                rec = records.get(image)
                if rec is None:
                    continue
                key = (rec.boxes[:, :4].tobytes(), rec.boxes[:, 6].tobytes())
                if key not in vectors:
                    rgb = load_image(root, rec) if rgb is None else rgb
                    vectors[key] = facing_net.vectors(rec, rgb)
                out[boxes][method][image] = replace(rec, extra=facing_net.with_vectors(rec.extra, vectors[key]))
    return out


def flatten(results: dict, detection: dict | None = None, root: str = "bev") -> dict[str, float]:
    """MLflow keys: the paired medians ``bev.<boxes>.<method>[.<population>].<metric>`` (METRICS) and the
    detection scores ``bev.<boxes>.<method>.<subset>.<metric>`` (DETECTION_METRICS; subsets ``all``,
    ``two_wheels``, ``one_wheel``, ``no_wheel``, ``<lo>-<hi>m``); ``root`` ``bev.shift``: the held-out domain's."""
    out = {}
    for boxes, by_method in (detection or {}).items():
        for method, by_subset in by_method.items():
            for subset, vals in by_subset.items():
                out.update({f"{root}.{boxes}.{method}.{subset}.{k}": float(vals[k])
                            for k in DETECTION_METRICS if not math.isnan(vals[k])})
    for boxes, by_method in results.items():
        for method, by_pop in by_method.items():
            for pop, vals in by_pop.items():
                prefix = f"{root}.{boxes}.{method}." + (f"{pop}." if pop else "")
                out.update({prefix + k: float(vals[k]) for k in METRICS if not math.isnan(vals[k])})
    return out


DETECTION_COLUMNS = (("ap", "AP"), ("ap_0p5m", "AP 0.5m"), ("ap_1m", "AP 1m"), ("ap_2m", "AP 2m"),
                     ("ap_4m", "AP 4m"), ("ate_m", "ATE m"), ("ase", "ASE"), ("aoe_deg", "AOE deg"),
                     ("aoe180_deg", "AOE mod 180 deg"), ("iou", "IoU"), ("center_err_median_m", "median centre m"),
                     ("recall", "recall"), ("precision", "precision"), ("recall_at_p95", "recall at 95 % precision"))


def render_detection(detection: dict, domain: str = "") -> list[str]:
    lines = ["Scored the nuScenes way on each frame's fused footprints: AP (%) with centre-distance matching at "
             "0.5/1/2/4 m over estimates ranked by confidence, `AP` their mean; ATE, ASE (1 - IoU of the aligned "
             "sizes), AOE over 360 deg and modulo 180 deg: recall-averaged true-positive errors at 2 m; IoU: mean BEV "
             "IoU of the 2 m matches; median centre m: their median centre distance; recall, precision (%) at 2 m of "
             "every estimate; recall at 95 % precision: at the confidence threshold that keeps estimates 95 % right. "
             "Subsets: `all`, `two_wheels`, `one_wheel`, `no_wheel` (wheels of the vehicle annotated in one image) "
             "within the range; distance bins.", ""]
    for boxes, by_method in detection.items():
        lines += [f"## {domain}{boxes} boxes: detection scores", "",
                  "| method | subset | vehicles | estimates | " + " | ".join(h for _, h in DETECTION_COLUMNS) + " |",
                  "|---|---|---:|---:|" + "---:|" * len(DETECTION_COLUMNS)]
        for subset in next(iter(by_method.values())):
            for method, by_subset in by_method.items():
                v = by_subset[subset]
                cells = " | ".join("-" if math.isnan(v[k]) else f"{v[k]:.3g}" for k, _ in DETECTION_COLUMNS)
                est = "-" if math.isnan(v["estimates"]) else str(int(v["estimates"]))
                lines.append(f"| {method} | {subset} | {int(v['vehicles'])} | {est} | {cells} |")
        lines.append("")
    return lines


def render_medians(report: dict, part: dict, domain: str = "") -> list[str]:
    lines = [f"## {domain}Paired medians", "",
             f"Matched by BEV centre distance <= {report['match_m']:g} m; medians over matched vehicles; recall in %. "
             f"Rows `all`, `paired` (two same-side wheels visible) and `hard` count vehicles within "
             f"{report['max_range_m']:g} m of the vehicle frame's origin (under the ego's rear axle); the other rows "
             f"are distance bins. Headings modulo 180 deg. {part['frames']} test frames.", ""]
    for boxes, by_method in part["results"].items():
        lines += [f"### {domain}{boxes} boxes", "", "| method | vehicles | " + " | ".join(METRICS) + " |",
                  "|---|---|" + "---:|" * len(METRICS)]
        pops = list(next(iter(by_method.values())))
        for pop in pops:
            for method, by_pop in by_method.items():
                v = by_pop[pop]
                cells = " | ".join("-" if math.isnan(v[k]) else f"{v[k]:.3g}" for k in METRICS)
                lines.append(f"| {method} ({pop or 'all'}) | {int(v['vehicles'])} | {cells} |")
        lines.append("")
    return lines


def render_facing(facing: dict, domain: str = "") -> list[str]:
    def agreement(v: dict) -> str:
        if "implied_acc" not in v:
            return ""
        weighed = f", so its votes counted x {v['trust']:.2f}" if v.get("trust", 1.0) < 1.0 else ""
        return (f"; without labels, two cameras' votes agree on {v['camera_agreement']:.1f} % of "
                f"{int(v['camera_pairs'])} camera pairs, as a network right for {v['implied_acc']:.1f} % would{weighed}")
    return [f"- {domain}{boxes} boxes: the facing vectors point within 90 deg of the true facing for "
            f"{v['acc']:.1f} % of the {int(v['vehicles'])} matched vehicles with 3D truth{agreement(v)}"
            for boxes, v in facing.items()]


def render_roles(roles: dict, domain: str = "") -> list[str]:
    return [f"- {domain}{boxes} boxes, `{v['method']}`: the wheels' front / rear roles are right for {v['acc']:.1f} % "
            f"of {int(v['relations'])} true relations as `deepword infer` writes them (from the footprint for "
            f"{v['footprint_share']:.0f} %), {v['facing_acc']:.1f} % from the facing vector alone (no calibration), "
            f"{v['network_acc']:.1f} % as the relation method named them"
            for boxes, v in roles.items()]


def render_report(report: dict, bcfg) -> str:
    lines = ["# Bird's-eye view: vehicle footprints from wheel contacts", ""]
    shift = report.get("shift") or {}
    facing = render_facing(report.get("facing", {})) + render_facing(shift.get("facing", {}), "held-out ")
    facing += render_roles(report.get("roles", {})) + render_roles(shift.get("roles", {}), "held-out ")
    lines += facing + ([""] if facing else [])
    lines += render_detection(report.get("detection", {}))
    lines += render_medians(report, report)
    shift = report.get("shift")
    if shift:
        lines += ["# Held-out domain (`shift_data`): the same prior, fitted on the in-domain train split", ""]
        lines += render_detection(shift["detection"], "held-out ") + render_medians(report, shift, "held-out ")
        lines += [f"- held-out: {n}" for n in shift["notes"]]
    p = report["prior"]
    scalars = ", ".join(f"{k}={v:g}" for k, v in p.items() if not isinstance(v, dict))
    table = f"; heading table: {len(p['heading'])} cells and axis classes" if p.get("heading") else ""
    lines += [f"Footprint prior fitted on the train split's 3D truth: {scalars}{table}", ""]
    lines += [f"- {n}" for n in report["notes"]]
    return "\n".join(lines) + "\n"


def end_to_end_method(report: Path) -> str:
    """The method evaluate headlined on detected boxes, from its ``report.json`` (the export bundle's end-to-end
    method; ``deepword`` for an evaluate output from before it recorded one)."""
    return json.loads(report.read_text()).get("end_to_end", "deepword") if report.is_file() else "deepword"


def write_figures(artifacts: Path, test: list[Record], truth: dict, cameras: dict, fused_by: dict,
                  prior: FootprintPrior, bcfg, detected_method: str = "deepword", prefix: str = "") -> list[Path]:
    """One figure per sample frame (the frames with the most vehicles in range, evenly spread): the truth alone,
    then a top view per method on ground-truth boxes, and ``detected_method`` (the end-to-end method) on detected
    boxes when there are (DeepWORD when that method has no footprints here); each with the truth under the four
    cameras' fused footprints (figure.py: colours by camera, arrows to the front, legend)."""
    by_frame = defaultdict(list)
    for rec in test:
        by_frame[rec.frame_id].append(rec)
    ranked = sorted(truth, key=lambda f: (-sum(t.range_m <= float(bcfg.max_range_m) for t in truth[f]), f))
    picks = ranked[:: max(1, len(ranked) // max(1, int(bcfg.figures)))][: int(bcfg.figures)]
    if ("detected", detected_method) not in fused_by:
        detected_method = "deepword"
    panels_of = [k for k in fused_by if k[0] == "gt"] + [k for k in fused_by if k == ("detected", detected_method)]
    paths = []
    for f in sorted(picks):
        recs = by_frame[f]
        rig = np.array([cameras[r.image].translation[:2] for r in recs])
        contacts = []
        for r in recs:
            wheels = r.boxes[r.class_ids == WHEEL]
            if len(wheels):
                xy, ok = wheel_contacts(cameras[r.image], wheels[:, :4], prior)
                contacts.append(xy[ok])
        contacts = np.concatenate(contacts) if contacts else np.zeros((0, 2))
        if not panels_of:
            continue
        true_boxes = [t.box for t in truth[f]]
        panels = [top_view(true_boxes, [], contacts, rig, f"frame {f}: truth ({len(true_boxes)} vehicles)",
                           float(bcfg.view_m))]
        for k in panels_of:
            panels.append(fused_top_view(true_boxes, fused_by[k][f], contacts, rig,
                                         f"frame {f}: {k[1]} ({k[0]} boxes)", float(bcfg.view_m)))
        path = artifacts / f"{prefix}top_view_{f:06d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(panel_grid(panels), cv2.COLOR_RGB2BGR))
        paths.append(path)
    return paths


__all__ = ["run", "check_3d", "Missing3DError"]
