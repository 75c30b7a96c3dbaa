"""Fingerprints of watched paths (user datasets on disk) for the cache key.

A file contributes the sha256 of its content (labels files are small); a directory contributes the
relative path, size and modification time (ns) of every file inside, never the contents: hashing
9,000 images on every run is the cost DVC users complain about most, and a changed image changes its
size or mtime. Relative paths are relative to the launch directory.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from pipeline.cache import file_sha256


def _dir_digest(root: Path) -> str:
    h = hashlib.sha256()
    entries: list[tuple[str, int, int]] = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for name in filenames:
            full = os.path.join(dirpath, name)
            st = os.stat(full)
            entries.append((os.path.relpath(full, root), st.st_size, st.st_mtime_ns))
    for rel, size, mtime in sorted(entries):
        h.update(f"{rel}\0{size}\0{mtime}\n".encode())
    return h.hexdigest()


def path_digest(path: str | os.PathLike) -> str:
    """Digest of one watched path; ``missing`` when it does not exist (the stage reports that)."""
    p = Path(path)
    if p.is_file():
        return "file:" + file_sha256(p)
    if p.is_dir():
        return "dir:" + _dir_digest(p)
    return "missing"


def watch_fingerprint(paths: list[str]) -> dict[str, str]:
    """{path as configured: digest} for every watched path."""
    return {str(p): path_digest(p) for p in paths}
