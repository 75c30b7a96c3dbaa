"""Split policy (docs/design.md §7): train/val/test by whole frames, easy/hard/mixed test subsets."""

from __future__ import annotations

import random

from deepword.word_format.record import Record

SPLITS = ("train", "val", "test")
SUBSETS = ("easy", "hard", "mixed")
# An optional split of a composed dataset (stages/data/compose.py): labelled images of another domain that no model
# trains, chooses a checkpoint or reports on, and that the operating-point search weighs beside a small val split
# (the generator's val beside a new camera's few val images; deepword/operating_point/search.py, Prior)
PRIOR_SPLIT = "val_prior"


def split_by_frame(records: list[Record], fractions: dict[str, float], seed: int) -> dict[str, list[str]]:
    """Assign whole frames (all cameras of one instant) to train/val/test; returns image paths per split."""
    frames = sorted({r.frame_id for r in records})
    random.Random(seed).shuffle(frames)
    total = sum(fractions[s] for s in SPLITS)
    n_val = round(len(frames) * fractions["val"] / total)
    n_test = round(len(frames) * fractions["test"] / total)
    if len(frames) >= 3:  # every split asked for gets a frame; a split of fraction 0 stays empty
        n_val = max(n_val, 1) if fractions["val"] > 0 else 0
        n_test = max(n_test, 1) if fractions["test"] > 0 else 0
    split_of = {}
    for i, f in enumerate(frames):
        split_of[f] = "test" if i < n_test else "val" if i < n_test + n_val else "train"
    return {s: [r.image for r in records if split_of[r.frame_id] == s] for s in SPLITS}


def difficulty_subsets(records: list[Record], seed: int, max_easy_vehicles: int = 3) -> dict[str, list[str]]:
    """easy: at most ``max_easy_vehicles`` annotated vehicles; hard: more; mixed: half easy, half hard
    (as many of each as the smaller kind has, halved, drawn with a fixed seed)."""
    easy = [r.image for r in records if r.n_vehicles <= max_easy_vehicles]
    hard = [r.image for r in records if r.n_vehicles > max_easy_vehicles]
    rng = random.Random(seed)
    half = max(min(len(easy), len(hard)) // 2, 1) if easy and hard else 0
    mixed = sorted(rng.sample(easy, half) + rng.sample(hard, half)) if half else sorted(easy or hard)
    return {"easy": easy, "hard": hard, "mixed": mixed}
