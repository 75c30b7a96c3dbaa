"""A WORD directory on disk as one source of a composed dataset (``data=mixed``: your camera's labelled images beside
the generator's; stages/data/compose.py).

The records are read and validated as ``data=word`` reads them (every image present, complete and of its record's
size). A composed dataset has one root, the data stage's output, so the images are linked into it under
``<source name>/`` (hard links; copied where the cache lies on another file system): a symbolic link would lead out of
the dataset root, which every reader refuses. Frame indices move by ``first_frame``, clear of the generator's, so that
no two sources share a frame (a frame groups the cameras of one instant). The source is split by frame with its own
``split`` fractions, as ``data=word`` splits it.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path

from deepword.word_format import LABELS_FILE, Record, read_records


def link_word_source(scfg: dict, name: str, out_dir: Path) -> list[Record]:
    """The source's records with their images linked under ``out_dir / name`` and their frames moved by
    ``first_frame``."""
    if not scfg.get("root") or scfg["root"] == "???":
        raise ValueError(f"data.sources.{name}.root: the WORD directory to compose (data.sources.{name}.root=PATH)")
    root = Path(scfg["root"]).expanduser().resolve()
    records = read_records(root / LABELS_FILE, root=root, check_images=True)
    offset = int(scfg.get("first_frame") or 0)
    out = []
    for rec in records:
        dest = out_dir / name / rec.image
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(root / rec.image, dest)
        except OSError:   # another file system (or no hard links there)
            shutil.copyfile(root / rec.image, dest)
        out.append(replace(rec, image=f"{name}/{rec.image}", frame_id=rec.frame_id + offset))
    return out
