"""A labelled pool of a new domain's frames, and the N images a run takes from it (``experiment=adapt``,
docs/adapt.md).

The pool is ``frames`` frames of the generator under the held-out domain's config (``generator``: the same families
as the held-out test set, ``shift.data``) on a random stream of its own (``stream``), with frame indices from
``first_frame`` on: other scenes than the held-out test set's and, since a rig is drawn from its frame index, other
lenses and mounts too. A *draw* is a fixed random order of the pool's frames (seeded by the root seed and the draw
number); a run of N images takes the first N images in that order (a frame's cameras in rig order, frames whose
images have no owner-member relation contribute none, the last frame possibly in part). So for one draw the N=25
images are the first 25 of the N=50 ones, and two draws take different frames. N counts images, what a team labels.

Only the frames a run takes are rendered (a frame is a pure function of the seed, the stream and its index), so the
pool's size costs nothing until a run needs it. Train and val are split by frame, again in draw order: the first
frame and then one in every ``1 / val_share`` frames go to val, so val is never empty and N=25's split is the
start of N=50's. The pool has no test split: the held-out test set (``shift_data``) is the test set.
"""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path

import numpy as np

from deepword.word_format import Record
from stages.data.synword import FrameWriter

POOL_STREAM_TAG = 0x9001  # the draw's random order: its own stream, apart from every frame's


class PoolTooSmall(ValueError):
    """N asks for more images than the pool's frames hold."""


def generator_cfg(pcfg: dict) -> dict:
    """The generator config of the pool's frames: ``generator`` with the pool's stream and frame count."""
    gen = dict(pcfg["generator"])
    gen.update(stream=int(pcfg["stream"]), frames=int(pcfg["frames"]))
    return gen


def draw_order(frames: int, first_frame: int, seed: int, draw: int) -> list[int]:
    """The pool's frame indices in draw ``draw``'s order (a permutation, fixed by seed and draw)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), POOL_STREAM_TAG, int(draw)]))
    return [int(first_frame) + int(i) for i in rng.permutation(int(frames))]


def val_positions(n_frames: int, val_share: float) -> set[int]:
    """Positions (in draw order) of the frames that go to val: 0 and then one in every 1 / val_share, so that
    a shorter take's split is the start of a longer one's (exact fractions: no float drift)."""
    share = Fraction(str(val_share))
    if not 0 < share < 1:
        raise ValueError(f"data pool val_share must be in (0, 1), got {val_share}")
    return {i for i in range(n_frames) if math.ceil((i + 1) * share) > math.ceil(i * share)}


def take_images(pcfg: dict, seed: int, out_dir: Path, progress: bool = True) -> tuple[list[Record], list[int]]:
    """Render the pool's frames in draw order into ``out_dir`` until ``images`` images are kept; returns those
    images' records (draw order) and the frames they came from (draw order). Images of frames rendered beyond the
    take are deleted. Raises ``PoolTooSmall`` when the pool's frames hold fewer images."""

    n, frames = int(pcfg["images"]), int(pcfg["frames"])
    where = "data.sources.pool"
    if n < 1:
        raise ValueError(f"{where}.images must be >= 1, got {n}")
    if n > 4 * frames:  # four cameras a frame: no draw can hold it
        raise PoolTooSmall(f"{where}.images={n} asks for more images than the pool's {frames} frames x 4 cameras "
                           f"hold; raise {where}.frames")
    order = draw_order(frames, int(pcfg["first_frame"]), seed, int(pcfg["draw"]))
    gen = generator_cfg(pcfg)
    taken: list[Record] = []
    used: list[int] = []
    rendered: list[Record] = []
    pos = 0
    with FrameWriter(gen, seed, out_dir, gen.get("workers"), most=frames) as writer:
        while len(taken) < n and pos < len(order):
            # ~3.5 kept images a frame: ask for a little more than the rest needs, in frame order (rigs shared)
            batch = order[pos:pos + max(2, math.ceil((n - len(taken)) / 3) + 1)]
            pos += len(batch)
            by_frame = dict(zip(sorted(batch), writer.write(sorted(batch), progress=progress), strict=True))
            for frame in batch:
                recs = by_frame[frame]
                rendered += recs
                if len(taken) < n and recs:
                    taken += recs[:n - len(taken)]
                    used.append(frame)
    kept = {r.image for r in taken}
    for rec in rendered:  # what a larger N would take, not this one
        if rec.image not in kept:
            (Path(out_dir) / rec.image).unlink(missing_ok=True)
    if len(taken) < n:
        raise PoolTooSmall(f"{where}.images={n}, but the pool's {frames} frames hold only {len(taken)} images with "
                           f"an owner-member relation (draw {pcfg['draw']}); raise {where}.frames")
    return taken, used


def pool_splits(records: list[Record], frames_in_order: list[int], val_share: float) -> dict[str, list[str]]:
    """train / val of the taken images by frame (``val_positions``); test empty."""
    val_frames = {frames_in_order[i] for i in val_positions(len(frames_in_order), val_share)}
    return {"train": [r.image for r in records if r.frame_id not in val_frames],
            "val": [r.image for r in records if r.frame_id in val_frames], "test": []}

