"""A dataset composed of several sources (a data config with ``sources``; ``data=adapt``, docs/adapt.md).

Each source is built as its own config would build it, into the one output directory: ``synword`` (the generator,
split by frame as ``data=synword`` splits it: the same records and the same seed give the same splits), ``pool``
(N images of a new domain's pool, ``stages.data.pool``) and ``word`` (a WORD directory on disk, its images linked
in, split by frame as ``data=word`` splits it: ``stages.data.word_source``). A source's ``use`` says which of its own
splits feed each composed split (``{train: train, val: val, test: null}``: its test images are not used);
``val_prior`` (``PRIOR_SPLIT``), optional, takes labelled images that only steady the detector's operating point
(``use: {val_prior: val}`` on the generator beside a new camera's few val images: deepword/operating_point/search.py).
``train_share`` repeats a source's train images (whole copies, at most ``max_repeat``) until they make about that
share of the composed train split: a few new images beside ~1,000 generated ones would otherwise weigh next to
nothing. The easy / hard / mixed subsets are drawn from the composed test split as for any dataset.

Sources must not share an image path or a frame index (the pool's and a WORD directory's frames start at
``first_frame``): every stage keys records by image and groups cameras by frame. Every record carries its source's
name (``data_source``).
"""

from __future__ import annotations

from pathlib import Path

from deepword.word_format import PRIOR_SPLIT, SPLITS, DatasetError, Record, difficulty_subsets, write_records
from stages.data.pool import pool_splits, take_images
from stages.data.stats import make_splits, split_metrics
from stages.data.synword import generate
from stages.data.word_source import link_word_source

SOURCE_KEY = "data_source"   # the record's extra key naming the source it came from
KINDS = ("synword", "pool", "word")


def build_sources(dcfg: dict, seed: int, out_dir: Path) -> tuple[list[Record], dict[str, list[str]], dict[str, float]]:
    """Build every source into ``out_dir`` and compose them: -> (records, splits with subsets, metrics)."""
    out_dir = Path(out_dir)
    sources = dcfg["sources"]
    if not sources:
        raise ValueError("data.sources is empty: a composed dataset needs at least one source")
    records: list[Record] = []
    owner_of_image: dict[str, str] = {}
    owner_of_frame: dict[int, str] = {}
    parts: dict[str, dict[str, list[str]]] = {}   # source -> composed split -> its images (each once)
    metrics: dict[str, float] = {}
    for name, scfg in sources.items():
        recs, own, extra = build_source(name, scfg, seed, out_dir)
        for rec in recs:
            if rec.image in owner_of_image:
                raise DatasetError(out_dir, None, f"data.sources.{name}",
                                   f"image {rec.image} is also source {owner_of_image[rec.image]!r}'s")
            if owner_of_frame.setdefault(rec.frame_id, name) != name:
                raise DatasetError(out_dir, None, f"data.sources.{name}",
                                   f"frame {rec.frame_id} is also source {owner_of_frame[rec.frame_id]!r}'s "
                                   "(give the source another first_frame)")
            owner_of_image[rec.image] = name
            rec.extra[SOURCE_KEY] = name
        records += recs
        parts[name] = route(name, scfg.get("use") or {}, own)
        metrics |= {f"data.{name}.{k}": v for k, v in extra.items()}
        metrics |= {f"data.{name}.{split}.images": float(len(imgs)) for split, imgs in parts[name].items()}
    repeats = train_repeats(sources, parts)
    splits = {split: [img for name in sources for img in parts[name][split] * (repeats[name] if split == "train" else 1)]
              for split in SPLITS}
    prior = [img for name in sources for img in parts[name][PRIOR_SPLIT]]
    if prior:   # written only where a source gives it images: every other dataset's splits.json is as before
        splits[PRIOR_SPLIT] = prior
    for split in SPLITS:
        if not splits[split]:
            raise DatasetError(out_dir, None, "data.sources",
                               f"no source gives the {split} split an image (set a source's use.{split})")
    by_image = {r.image: r for r in records}
    splits |= difficulty_subsets([by_image[i] for i in splits["test"]], seed, int(dcfg["max_easy_vehicles"]))
    write_records(out_dir / "labels.jsonl", records)
    once = {k: list(dict.fromkeys(v)) for k, v in splits.items()}   # statistics of distinct images
    metrics |= split_metrics(records, once)
    metrics |= {f"data.{name}.train_repeat": float(k) for name, k in repeats.items()}
    metrics["data.train.images_with_repeats"] = float(len(splits["train"]))
    return records, splits, metrics


def build_source(name: str, scfg: dict, seed: int, out_dir: Path) -> tuple[list[Record], dict[str, list[str]], dict]:
    """One source's records (written under ``out_dir``), its own train/val/test, and metrics about it."""
    kind = scfg.get("name")
    if kind == "synword":

        recs = generate(scfg, seed, out_dir, workers=scfg.get("workers"))
        own = make_splits(recs, scfg["split"], seed, int(scfg["max_easy_vehicles"]))
        return recs, {s: own[s] for s in SPLITS}, {}
    if kind == "pool":

        recs, frames = take_images(scfg, seed, out_dir)
        return recs, pool_splits(recs, frames, float(scfg["val_share"])), {"images": float(len(recs)),
                                                                            "frames": float(len(frames))}
    if kind == "word":

        recs = link_word_source(scfg, name, out_dir)
        own = make_splits(recs, scfg["split"], seed, int(scfg["max_easy_vehicles"]))
        return recs, {s: own[s] for s in SPLITS}, {"images": float(len(recs))}
    raise ValueError(f"data.sources.{name}.name: {kind!r} cannot be composed (one of {', '.join(KINDS)})")


def route(name: str, use: dict, own: dict[str, list[str]]) -> dict[str, list[str]]:
    """The source's images per composed split: ``use`` maps a composed split to one of the source's (or null)."""
    composed = (*SPLITS, PRIOR_SPLIT)
    unknown = sorted(set(use) - set(composed))
    if unknown:
        raise ValueError(f"data.sources.{name}.use: unknown split {unknown[0]!r} (have {', '.join(composed)})")
    out = {}
    for split in composed:
        theirs = use.get(split)
        if theirs is not None and theirs not in own:
            raise ValueError(f"data.sources.{name}.use.{split}: {theirs!r} is not a split of the source "
                             f"({', '.join(own)})")
        out[split] = list(own[theirs]) if theirs is not None else []
    return out


def train_repeats(sources: dict, parts: dict[str, dict[str, list[str]]]) -> dict[str, int]:
    """Copies of each source's train images: ``train_share`` s asks for about s of the composed train split
    (k x own / (k x own + others) ~ s), at least one copy and at most ``max_repeat``."""
    out = {}
    for name, scfg in sources.items():
        share, own = scfg.get("train_share"), len(parts[name]["train"])
        others = sum(len(parts[o]["train"]) for o in sources if o != name)
        if share is None or not own or not others:
            out[name] = 1
            continue
        if not 0 < float(share) < 1:
            raise ValueError(f"data.sources.{name}.train_share must be in (0, 1) or null, got {share}")
        k = round(float(share) * others / ((1 - float(share)) * own))
        out[name] = int(max(1, min(k, int(scfg.get("max_repeat") or k or 1))))
    return out
