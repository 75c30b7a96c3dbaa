"""Contact sheet of frames (all four cameras) with Fig. 5-style labels, from any WORD-style dataset.

    python -m stages.data.show ROOT [--n 4] [--out sheet.png]

ROOT is a dataset root (``labels.jsonl``) or a data stage output (``dataset.json``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from deepword.overlay import contact_sheet, draw_relations
from deepword.word_format import CAMERAS, LABELS_FILE, Record, load_image, read_records


def frame_sheet(root: Path, records: list[Record], n_frames: int, out_path: Path) -> Path:
    """Write a sheet of the first ``n_frames`` frames, one row each, cameras in front/left/right/rear order
    (a blank tile where a frame has no image for a camera)."""
    frames: dict[int, dict[str, Record]] = {}
    for rec in records:
        frames.setdefault(rec.frame_id, {})[rec.camera] = rec
    tiles = []
    for fid in sorted(frames)[:n_frames]:
        recs = frames[fid]
        size = next(iter(recs.values()))
        for cam in CAMERAS:
            if cam in recs:
                tiles.append(draw_relations(load_image(root, recs[cam]), recs[cam]))
            else:
                tiles.append(np.zeros((size.height, size.width, 3), np.uint8))
    sheet = contact_sheet(tiles, len(CAMERAS))
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return out_path


def dataset_root(path: Path) -> Path:
    """The directory holding ``labels.jsonl``: ``path`` itself or the root a ``dataset.json`` names."""
    index = path / "dataset.json"
    if index.is_file():
        return (path / json.loads(index.read_text())["root"]).resolve()
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Contact sheet of a WORD-style dataset (Fig. 5 overlays)")
    parser.add_argument("root", type=Path)
    parser.add_argument("--n", type=int, default=4, help="number of frames (rows)")
    parser.add_argument("--out", type=Path, default=Path("sheet.png"))
    args = parser.parse_args(argv)
    root = dataset_root(args.root)
    out = frame_sheet(root, read_records(root / LABELS_FILE, root=root), args.n, args.out)
    print(out)


if __name__ == "__main__":
    main()
