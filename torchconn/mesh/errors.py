""":class:`MeshError` and the helpers that name offending elements in its messages."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["MeshError"]


class MeshError(ValueError):
    """Invalid mesh or complex (shape, range, geometry or topology), or a lookup of elements
    the mesh does not have; the message names the offending elements."""


def _few(idx, k: int = 5) -> str:
    """``"[3, 17, 20, ...] (count 12)"`` for an index array."""
    idx = np.asarray(idx).reshape(-1)
    head = ", ".join(str(int(i)) for i in idx[:k])
    more = ", ..." if idx.size > k else ""
    return f"[{head}{more}] (count {idx.size})"


def _few_rows(rows, k: int = 5) -> str:
    """``"(3, 17), (4, 9), ... (count 12)"`` for a 2-D integer array."""
    rows = np.asarray(rows)
    head = ", ".join("(" + ", ".join(str(int(x)) for x in r) + ")" for r in rows[:k])
    more = ", ..." if len(rows) > k else ""
    return f"{head}{more} (count {len(rows)})"

def _checked_path(path, suffixes, kind: str) -> tuple[Path, str]:
    """``(Path, lower-case suffix)``; MeshError for an unsupported suffix, FileNotFoundError if absent."""
    path = Path(path)
    suf = path.suffix.lower()
    if suf not in suffixes:
        raise MeshError(f"unsupported {kind} suffix {suf!r} of {path}; supported: {', '.join(suffixes)}")
    if not path.exists():
        raise FileNotFoundError(f"no such {kind} file: {path}")
    return path, suf
