"""Per-tet frame files that hex meshers read.

- ``.fra`` (CubeCover, HexFrameFlow): :func:`write_fra` / :func:`read_fra`. Line 1 ``FRA 1``,
  line 2 ``<T> 3 4``, then for each tet three lines, one frame axis each, ``x y z``.
- ``.frame`` (mouette's ``FrameField3DCells.read_from_file`` / ``export_frames_to_file``):
  :func:`write_mouette_frame` / :func:`read_mouette_frame`. Line 1 ``FRAME``, line 2 ``<T>``,
  then one line per tet ``a_x a_y a_z b_x b_y b_z c_x c_y c_z`` (the three axes in turn), and a
  final ``END``.

Convention: ``frames (T, 3, 3)``, ``frames[t][:, k]`` is axis ``k`` of tet ``t`` in world
coordinates (the columns, as everywhere in :mod:`torchconn.frames`); both formats list the axes
in the order ``k = 0, 1, 2``, in the order of ``mesh.tets``. Numbers are written with
``repr``-exact 17 significant digits, so a float64 field reads back bit for bit.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

__all__ = ["write_fra", "read_fra", "write_mouette_frame", "read_mouette_frame"]


def _frames_np(frames, n_tets: int | None) -> np.ndarray:
    a = frames.detach().cpu().numpy() if torch.is_tensor(frames) else np.asarray(frames)
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ValueError(f"frames must have shape (T, 3, 3), got {a.shape}")
    if n_tets is not None and a.shape[0] != n_tets:
        raise ValueError(f"frames has {a.shape[0]} rows but the mesh has T = {n_tets} tets (per-tet frames expected)")
    if not np.isfinite(a).all():
        bad = np.nonzero(~np.isfinite(a).reshape(a.shape[0], -1).all(axis=1))[0]
        raise ValueError(f"frames has NaN/inf entries at tets {bad[:10].tolist()}")
    return a.astype(np.float64)


def _n_tets(mesh) -> int | None:
    return None if mesh is None else int(mesh.tets.shape[0])


def write_fra(path, frames, mesh=None) -> Path:
    """Write per-tet frames ``(T, 3, 3)`` (axes as columns) as a ``.fra`` file.

    ``mesh`` (optional) checks that there is one frame per tet. Returns the path.
    """
    a = _frames_np(frames, _n_tets(mesh))
    axes = np.swapaxes(a, 1, 2).reshape(-1, 3)  # row 3t+k = axis k of tet t
    path = Path(path)
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"FRA 1\n{a.shape[0]} 3 4\n")
        np.savetxt(fh, axes, fmt="%.17g")
    return path


def _tokens(path: Path, magic: str) -> tuple[list[str], list[str]]:
    with open(path, encoding="ascii", errors="replace") as fh:
        lines = [ln.strip() for ln in fh if ln.strip()]
    if not lines or lines[0].split() != magic.split():
        first = lines[0] if lines else "<empty file>"
        raise ValueError(f"{path}: line 1 must be {magic!r}, got {first!r}")
    if len(lines) < 2:
        raise ValueError(f"{path}: line 2 (the counts) is missing")
    return lines, lines[1].split()


def _parse_rows(path: Path, rows: list[str], width: int, first_line: int) -> np.ndarray:
    out = np.empty((len(rows), width))
    for r, ln in enumerate(rows):
        parts = ln.split()
        try:
            if len(parts) != width:
                raise ValueError
            out[r] = [float(x) for x in parts]
        except ValueError:
            raise ValueError(f"{path}: line {first_line + r} must hold {width} numbers, got {ln!r}") from None
    return out


def read_fra(path, *, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """Read a ``.fra`` file into ``frames (T, 3, 3)`` (axes as columns).

    Raises:
        ValueError: a wrong header (naming the line), a count that does not match the rows,
            or a row that is not three numbers.
    """
    path = Path(path)
    lines, head = _tokens(path, "FRA 1")
    if len(head) != 3 or head[1:] != ["3", "4"] or not head[0].isdigit():
        raise ValueError(f"{path}: line 2 must be '<number of tets> 3 4', got {lines[1]!r}")
    T = int(head[0])
    rows = lines[2:]
    if len(rows) != 3 * T:
        raise ValueError(f"{path}: {T} tets need {3 * T} axis lines after the header, found {len(rows)}")
    axes = _parse_rows(path, rows, 3, 3).reshape(T, 3, 3)  # [t, k, :] = axis k
    return torch.as_tensor(np.swapaxes(axes, 1, 2).copy(), dtype=dtype, device=device)


def write_mouette_frame(path, frames, mesh=None) -> Path:
    """Write per-tet frames ``(T, 3, 3)`` (axes as columns) as mouette's ``.frame`` file.

    ``mesh`` (optional) checks that there is one frame per tet. Returns the path.
    """
    a = _frames_np(frames, _n_tets(mesh))
    rows = np.swapaxes(a, 1, 2).reshape(-1, 9)  # a_x a_y a_z b_x ... per tet
    path = Path(path)
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"FRAME\n{a.shape[0]}\n")
        np.savetxt(fh, rows, fmt="%.17g")
        fh.write("END\n")
    return path


def read_mouette_frame(path, *, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """Read mouette's ``.frame`` file into ``frames (T, 3, 3)`` (axes as columns); the final
    ``END`` line is optional, as in mouette's reader.

    Raises:
        ValueError: a wrong header, a count that does not match the rows, or a bad row.
    """
    path = Path(path)
    lines, head = _tokens(path, "FRAME")
    if len(head) != 1 or not head[0].isdigit():
        raise ValueError(f"{path}: line 2 must be the number of frames, got {lines[1]!r}")
    T = int(head[0])
    rows = lines[2:]
    if rows and rows[-1] == "END":
        rows = rows[:-1]
    if len(rows) != T:
        raise ValueError(f"{path}: {T} frames announced, found {len(rows)} frame lines")
    axes = _parse_rows(path, rows, 9, 3).reshape(T, 3, 3)
    return torch.as_tensor(np.swapaxes(axes, 1, 2).copy(), dtype=dtype, device=device)
