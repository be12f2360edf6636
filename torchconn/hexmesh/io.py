"""Files of the hex-meshing stage: the map in libHexEx's ``.hexex`` format, hex meshes as
``.vtu`` / ``.mesh``, and a picture of a hex mesh (``../shared/HEXMESH.md``, "Formats").

- ``.hexex`` (libHexEx's input; CubeCover and HexHex read it too): :func:`write_hexex` /
  :func:`read_hexex`. Line 1 ``n``, then ``n`` lines ``x y z``; then ``m``, then ``m`` lines of
  4 vertex indices (0-based, ``det(p1 - p0, p2 - p0, p3 - p0) > 0``) followed by the 4 corners'
  ``u v w`` (16 numbers a line). Numbers are written as Python's shortest round-trip ``repr``
  (``0.1``, ``0.3333333333333333``, ``-0.0``, ``1e-300``), so a float64 map reads back bit for
  bit. (C++ stream extraction, as in libHexEx, may refuse subnormal numbers below ``2.2e-308``;
  a map has none in practice.)
- Hex meshes ``points (N, 3)`` float64, ``hexes (H, 8)`` int64 in VTK order (``0-1-2-3`` one
  face, ``4-5-6-7`` the opposite one, ``4`` above ``0``, positively oriented):
  :func:`write_hex_mesh` / :func:`read_hex_mesh` as VTK XML ``.vtu`` (``hexahedron`` cells) or
  MEDIT ``.mesh`` (``Hexahedra``, the same vertex order) through meshio.
- :func:`plot_hex_mesh`: a PNG of the boundary quads, lightly shaded, and the irregular
  (singular) interior edges drawn boldly, coloured by valence, from two opposite views.
- After an invalid map, what shows where it fails: :func:`write_failure_vtu` (the input tets with
  the flags of :func:`~torchconn.hexmesh.report.tet_flags` and the singular graph as lines) and
  :func:`plot_failure` (the input's boundary with the flagged tets and the singular graph).

Every writer is atomic: the file is written to a temporary file in the target's directory and
moved over the target with ``os.replace``; on an error the temporary file is removed and nothing
is left half-written (an existing target is kept as it was). Readers raise ``ValueError`` naming
the file (and, for ``.hexex``, the line) of malformed content, ``FileNotFoundError`` for a
missing file. meshio and matplotlib are imported inside the functions that need them.
"""
from __future__ import annotations

import math
import os
import tempfile
import textwrap
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..mesh.io import _guarded
from .quality import HexQuality, _index_rows, hex_quality
from .report import FLAGS, singular_lines, tet_flags, verdict as _verdict

__all__ = ["write_hexex", "read_hexex", "write_hex_mesh", "read_hex_mesh", "plot_hex_mesh", "write_failure_vtu",
           "plot_failure", "HEX_MESH_SUFFIXES", "PLOT_MAX_QUADS", "PLOT_MAX_EDGES", "PLOT_QUAD_OUTLINES_MAX"]

#: Hex mesh files :func:`write_hex_mesh` / :func:`read_hex_mesh` know, with their meshio format.
HEX_MESH_SUFFIXES = {".vtu": "vtu", ".mesh": "medit"}
#: :func:`plot_hex_mesh` draws at most this many boundary quads (an even subsample beyond,
#: said in the picture's caption) ...
PLOT_MAX_QUADS = 40_000
#: ... at most this many singular edges (likewise) ...
PLOT_MAX_EDGES = 20_000
#: ... and outlines the quads only up to this many (beyond, the shading alone shows the shape;
#: from a fifth of it on, with hairlines).
PLOT_QUAD_OUTLINES_MAX = 12_000


# ----------------------------------------------------------------------------- atomic writes
def _atomic(path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary path in ``path``'s directory (same suffix), then move
    it over ``path``. On any error the temporary file is removed and the error re-raised."""
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write {path}: the directory {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp creates 0600; give the usual permissions
        write(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
    return path


def _array(x, name: str) -> np.ndarray:
    return x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)


def _floats(x, name: str, shape: tuple) -> np.ndarray:
    a = _array(x, name)
    if a.ndim != len(shape) or any(s is not None and a.shape[i] != s for i, s in enumerate(shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if a.size and (not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating)):
        raise ValueError(f"{name} must hold real numbers, got dtype {a.dtype}")
    a = a.astype(np.float64)
    bad = np.nonzero(~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1))[0] if a.size else []
    if len(bad):
        raise ValueError(f"{name} has NaN/inf entries at rows {bad[:10].tolist()} (count {len(bad)})")
    return a


def _indices(x, name: str, k: int, n: int) -> np.ndarray:
    return _index_rows(x, name, k, n)


# ----------------------------------------------------------------------------- .hexex
def _lines(values: np.ndarray, per_line: int) -> str:
    """``values`` (flat) as lines of ``per_line`` shortest-repr numbers."""
    toks = list(map(repr, values.reshape(-1).tolist()))
    return "".join(" ".join(toks[i:i + per_line]) + "\n" for i in range(0, len(toks), per_line))


def write_hexex(path, vertices, tets, uvw) -> Path:
    """Write a tet mesh and its per-tet-corner map as libHexEx's ``.hexex`` (module docstring).

    Args:
        path: the file to write (atomically).
        vertices: ``(V, 3)`` positions.
        tets: ``(T, 4)`` vertex indices, positively oriented.
        uvw: ``(T, 4, 3)``: ``uvw[t, k]`` the parameter ``(u, v, w)`` of corner ``k`` of tet ``t``.

    Returns the path.

    Raises:
        ValueError: wrong shapes or dtypes, NaN/inf values, indices out of range, or tets that
            are not positively oriented (naming them), before anything is written.
    """
    V = _floats(vertices, "vertices", (None, 3))
    T = _indices(tets, "tets", 4, V.shape[0])
    U = _floats(uvw, "uvw", (T.shape[0], 4, 3))
    P = V[T]
    det = np.einsum("ti,ti->t", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), P[:, 3] - P[:, 0])
    bad = np.nonzero(~(det > 0))[0]
    if bad.size:
        raise ValueError(f"tets {bad[:10].tolist()} (count {bad.size}) are not positively oriented "
                         f"(det(p1-p0, p2-p0, p3-p0) <= 0), which .hexex requires")
    par = list(map(repr, U.reshape(-1).tolist()))
    idx = T.tolist()
    text = (f"{V.shape[0]}\n" + _lines(V, 3) + f"{T.shape[0]}\n"
            + "".join(f"{a} {b} {c} {d} " + " ".join(par[12 * t:12 * t + 12]) + "\n"
                      for t, (a, b, c, d) in enumerate(idx)))
    data = text.encode("ascii")
    return _atomic(path, lambda tmp: tmp.write_bytes(data))


def _parse_block(path: Path, lines: list, numbers: list, start: int, count: int, width: int, what: str,
                 n_int: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Parse ``count`` lines of ``width`` numbers starting at entry ``start`` of ``lines``
    (``numbers`` are their 1-based line numbers): ``(ints (count, n_int), floats (count, width - n_int))``.
    The fast path converts all tokens at once; on any failure the lines are checked one by one
    so that the error names the first bad line."""
    block = lines[start:start + count]
    if len(block) < count:
        where = numbers[-1] if numbers else 0
        raise ValueError(f"{path}: {count} {what} lines announced, the file ends after {len(block)} "
                         f"(last line {where})")
    if _widths_ok(block, width):
        with warnings.catch_warnings():  # numpy warns (or raises) when a token is no number
            warnings.simplefilter("error", DeprecationWarning)
            try:
                vals = np.fromstring(" ".join(block), dtype=np.float64, sep=" ")
            except (ValueError, DeprecationWarning):
                vals = None
        if vals is not None and vals.size == count * width:
            vals = vals.reshape(count, width)
            ints = vals[:, :n_int]
            if np.isfinite(vals).all() and (ints == np.round(ints)).all() and (np.abs(ints) < 2.0 ** 53).all():
                return ints.astype(np.int64), vals[:, n_int:]
    for k, ln in enumerate(block):
        parts = ln.split()
        where = f"{path}, line {numbers[start + k]}"
        if len(parts) != width:
            raise ValueError(f"{where}: a {what} line must hold {width} numbers, got {len(parts)}: {ln.strip()!r}")
        for i, tok in enumerate(parts):
            if not (_is_index(tok) if i < n_int else _is_finite(tok)):
                kind = "an integer vertex index" if i < n_int else "a finite number"
                raise ValueError(f"{where}: entry {i + 1} of the {what} line must be {kind}, got {tok!r}")
    raise ValueError(f"{path}: malformed {what} lines {numbers[start]}-{numbers[start + count - 1]}")


def _is_index(tok: str) -> bool:
    try:
        x = float(tok)
    except ValueError:
        return False
    return math.isfinite(x) and x == round(x)


def _is_finite(tok: str) -> bool:
    try:
        return bool(np.isfinite(float(tok)))
    except ValueError:
        return False


def _widths_ok(block: list, width: int) -> bool:
    counts = np.fromiter((len(b.split()) for b in block), dtype=np.int64, count=len(block))
    return bool((counts == width).all())


def _count(path: Path, lines: list, numbers: list, i: int, what: str) -> int:
    if i >= len(lines):
        end = numbers[-1] if numbers else 0
        raise ValueError(f"{path}: the number of {what} is missing (the file ends at line {end})")
    tok = lines[i].split()
    if len(tok) != 1 or not tok[0].isdigit():
        raise ValueError(f"{path}, line {numbers[i]}: expected the number of {what} (one non-negative integer), "
                         f"got {lines[i].strip()!r}")
    return int(tok[0])


def read_hexex(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a ``.hexex`` file: ``(vertices (V, 3) float64, tets (T, 4) int64, uvw (T, 4, 3)
    float64)`` (numpy). Blank lines are skipped; numbers are parsed correctly rounded (what
    :func:`write_hexex` wrote reads back bit for bit); vertex indices must be whole numbers.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line: a count that is not a non-negative integer, a
            line with the wrong number of entries or a non-number, fewer lines than announced,
            content after the last tet, vertex indices out of range.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such .hexex file: {path}")
    try:
        raw = path.read_text(encoding="ascii")
    except UnicodeDecodeError as exc:
        line = path.read_bytes()[:exc.start].count(b"\n") + 1
        raise ValueError(f"{path}, line {line}: not a text .hexex file (a non-ASCII byte)") from None
    numbers, lines = [], []
    for k, ln in enumerate(raw.splitlines(), start=1):
        if ln.strip():
            numbers.append(k)
            lines.append(ln)
    if not lines:
        raise ValueError(f"{path}: empty file (a .hexex file starts with the number of vertices)")
    n = _count(path, lines, numbers, 0, "vertices")
    _, V = _parse_block(path, lines, numbers, 1, n, 3, "vertex")
    m = _count(path, lines, numbers, 1 + n, "tets")
    T, U = _parse_block(path, lines, numbers, 2 + n, m, 16, "tet", n_int=4)
    end = 2 + n + m
    if end < len(lines):
        raise ValueError(f"{path}, line {numbers[end]}: unexpected content after the {m} announced tets: "
                         f"{lines[end].strip()[:80]!r}")
    bad = np.nonzero(((T < 0) | (T >= n)).any(axis=1))[0]
    if bad.size:
        raise ValueError(f"{path}, line {numbers[2 + n + int(bad[0])]}: tet {int(bad[0])} has vertex indices outside "
                         f"[0, {n}): {T[bad[0]].tolist()} ({bad.size} such tets)")
    return V.reshape(n, 3), T.reshape(m, 4), U.reshape(m, 4, 3)


# ----------------------------------------------------------------------------- .vtu / .mesh
def _hex_suffix(path: Path) -> str:
    suf = path.suffix.lower()
    if suf not in HEX_MESH_SUFFIXES:
        raise ValueError(f"unsupported hex mesh suffix {suf!r} of {path}; supported: {', '.join(HEX_MESH_SUFFIXES)}")
    return HEX_MESH_SUFFIXES[suf]


def write_hex_mesh(path, points, hexes) -> Path:
    """Write a hex mesh as ``.vtu`` (VTK ``hexahedron`` cells) or ``.mesh`` (MEDIT
    ``Hexahedra``) through meshio, atomically; the vertex order is kept as given (VTK order).

    Args:
        path: ``*.vtu`` or ``*.mesh``.
        points: ``(N, 3)`` positions; hexes: ``(H, 8)`` vertex indices.

    Raises:
        ValueError: an unsupported suffix, wrong shapes or dtypes, NaN/inf points or indices out
            of range, before anything is written.
    """
    import meshio

    path = Path(path)
    fmt = _hex_suffix(path)
    P = _floats(points, "points", (None, 3))
    Hx = _indices(hexes, "hexes", 8, P.shape[0])
    mesh = meshio.Mesh(P, [("hexahedron", Hx)])
    return _atomic(path, lambda tmp: meshio.write(str(tmp), mesh, file_format=fmt))


def read_hex_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``.vtu`` or ``.mesh`` hex mesh: ``(points (N, 3) float64, hexes (H, 8) int64)``
    (numpy). Lower-dimensional cells (a MEDIT file's boundary quads, say) are ignored.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: an unsupported suffix, content meshio cannot read (with
            meshio's message), no hexahedra, other volume cells, or indices out of range.
    """
    import meshio

    path = Path(path)
    fmt = _hex_suffix(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such hex mesh file: {path}")
    # meshio ends the interpreter (sys.exit) on some malformed files: the mesh loaders' guard
    # turns any reader failure, with what it printed, into a message
    m, err = _guarded(lambda p: meshio.read(str(p), file_format=fmt), path)
    if err is not None:
        raise ValueError(f"{path}: cannot be read as a {fmt} hex mesh: {err}")
    volume = {c.type for c in m.cells} & {"tetra", "wedge", "pyramid", "hexahedron20", "hexahedron27", "tetra10"}
    if volume:
        raise ValueError(f"{path}: holds volume cells other than hexahedra ({', '.join(sorted(volume))}); "
                         f"a hex mesh has hexahedra only")
    blocks = [np.asarray(c.data, dtype=np.int64) for c in m.cells if c.type == "hexahedron"]
    if not blocks:
        kinds = sorted({c.type for c in m.cells}) or ["none"]
        raise ValueError(f"{path}: no hexahedra (cells: {', '.join(kinds)})")
    P = np.asarray(m.points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"{path}: points must be 3-D, got shape {P.shape}")
    Hx = np.concatenate(blocks)
    bad = np.nonzero(((Hx < 0) | (Hx >= P.shape[0])).any(axis=1))[0]
    if bad.size:
        raise ValueError(f"{path}: hexahedra {bad[:10].tolist()} (count {bad.size}) have vertex indices outside "
                         f"[0, {P.shape[0]})")
    return P, Hx


# ----------------------------------------------------------------------------- picture
_VALENCE_COLOURS = {1: "tab:green", 2: "tab:olive", 3: "tab:blue", 5: "tab:red", 6: "tab:purple"}


def _subsample(n: int, cap: int) -> tuple[np.ndarray, int]:
    """Indices of an even subsample of ``range(n)`` of at most ``cap`` elements, and the stride."""
    stride = max(1, -(-n // cap))
    return np.arange(0, n, stride), stride


def _wrapped(text: str, width: int = 125, most: int = 5) -> list[str]:
    """``text`` as title lines of at most ``width`` characters; beyond ``most`` lines cut with '...'."""
    lines = textwrap.wrap(text, width)
    return lines if len(lines) <= most else lines[:most - 1] + [lines[most - 1][:width - 4] + " ..."]


def _top(lines: list, height_in: float) -> float:
    """The axes' top (figure fraction) below a suptitle of ``lines`` at 10 pt on a figure
    ``height_in`` inches high, leaving room for the views' own titles."""
    return 1.0 - (len(lines) * 10 * 1.25 / 72 + 0.45) / height_in


def plot_hex_mesh(path_png, points, hexes, quality: HexQuality | None = None, *, title: str | None = None,
                  verdict: str | None = None) -> Path:
    """Write a PNG of a hex mesh: its boundary quads lightly shaded (see-through) and its
    irregular interior edges drawn boldly, coloured by valence (3 blue, 5 red, ...), with a
    legend of the counts, the verdict and the mesh's figures in the title, from two opposite views.

    Args:
        path_png: the file to write (atomically).
        points, hexes: the hex mesh (VTK order).
        quality: its :func:`~torchconn.hexmesh.quality.hex_quality` (computed when ``None``).
        title: a first title line (e.g. the model's name).
        verdict: the verdict line (a run's :func:`~torchconn.hexmesh.report.verdict` ``text``, which
            judges the map too); default: the verdict of ``quality`` alone.

    Large meshes stay readable: beyond :data:`PLOT_QUAD_OUTLINES_MAX` boundary quads the quads
    are drawn without outlines, beyond :data:`PLOT_MAX_QUADS` quads and
    :data:`PLOT_MAX_EDGES` singular edges an even subsample is drawn and the caption says so.
    matplotlib's Agg canvas is used directly (the global backend is left alone).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    P = _floats(points, "points", (None, 3))
    Hx = _indices(hexes, "hexes", 8, P.shape[0])
    q = quality if quality is not None else hex_quality(P, Hx)
    quads = q.boundary_quads
    Q = quads.shape[0]
    qi, q_stride = _subsample(Q, PLOT_MAX_QUADS)
    quads = quads[qi]
    S = q.irregular_edges.shape[0]
    ei, e_stride = _subsample(S, PLOT_MAX_EDGES)
    edges, valence = q.irregular_edges[ei], q.irregular_valence[ei]

    used = np.unique(Hx) if Hx.size else np.zeros(0, np.int64)
    lo = P[used].min(axis=0) if used.size else np.zeros(3)
    hi = P[used].max(axis=0) if used.size else np.ones(3)
    span = np.maximum(hi - lo, 1e-12 * max(float(np.max(hi - lo)), 1.0))

    poly = P[quads]  # (Q', 4, 3)
    n = np.cross(poly[:, 2] - poly[:, 0], poly[:, 3] - poly[:, 1])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    shade = 0.45 + 0.5 * np.abs(n @ light)
    face = np.concatenate([np.outer(shade, [0.78, 0.80, 0.84]), np.full((len(quads), 1), 0.22)], axis=1)
    outline = 0.0 if Q > PLOT_QUAD_OUTLINES_MAX else (0.3 if 5 * Q <= PLOT_QUAD_OUTLINES_MAX else 0.1)
    bold = 3.0 if S <= 200 else 2.0 if S <= 2000 else 1.0 if S <= 10_000 else 0.6

    fig = Figure(figsize=(13, 6.8), dpi=110)
    FigureCanvasAgg(fig)
    vals = sorted(set(valence.tolist()))
    for k, azim in enumerate((-60.0, 120.0)):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        if len(quads):
            ax.add_collection3d(Poly3DCollection(poly, facecolors=face, edgecolors=(0.35, 0.37, 0.42, 0.35),
                                                 linewidths=outline))
        for v in vals:
            sel = valence == v
            seg = P[edges[sel]]
            ax.add_collection3d(Line3DCollection(seg, colors=_VALENCE_COLOURS.get(v, "tab:orange"), linewidths=bold))
        ax.set_xlim(lo[0], lo[0] + span[0])
        ax.set_ylim(lo[1], lo[1] + span[1])
        ax.set_zlim(lo[2], lo[2] + span[2])
        ax.set_box_aspect(tuple(span / span.max()))
        ax.view_init(elev=25.0, azim=azim)
        ax.set_axis_off()
        ax.set_title(f"view from azimuth {azim:g}°", fontsize=9)
    counts = q.irregular_valence_counts
    handles = [Line2D([], [], color=_VALENCE_COLOURS.get(v, "tab:orange"), lw=3,
                      label=f"valence {v}: {counts.get(v, 0)} edges") for v in sorted(counts)]
    if not handles:
        handles = [Line2D([], [], color="none", label="no irregular interior edge")]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 6), frameon=False, fontsize=10,
               title="irregular (singular) interior edges, by the number of hexes around them")
    if verdict is None:
        verdict = _verdict({"quality": q.as_dict()})["text"]
    figures = [f"{q.n_hexes} hexes, {Q} boundary quads"]
    if q.n_hexes:
        figures.append(f"scaled Jacobian min {q.sj_min:.3f} / mean {q.sj_mean:.3f}")
    if q.n_interior_edges:
        figures.append(f"irregular interior edges {q.n_irregular_interior_edges} of {q.n_interior_edges} "
                       f"({q.irregular_fraction:.1%})")
    if q.hausdorff_rel is not None:
        figures.append(f"Hausdorff {q.hausdorff_rel:.2%} of the diagonal, volume ratio {q.volume_ratio:.3f}")
    lines = ([title] if title else []) + _wrapped(verdict) + ["; ".join(figures)]
    fig.suptitle("\n".join(lines), fontsize=10)
    notes = []
    if q_stride > 1:
        notes.append(f"1 in {q_stride} boundary quads drawn")
    if e_stride > 1:
        notes.append(f"1 in {e_stride} irregular edges drawn")
    if notes:
        fig.text(0.99, 0.01, "; ".join(notes), ha="right", va="bottom", fontsize=8, color="0.3")
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.1, top=_top(lines, 6.8), wspace=0.0)
    return _atomic(path_png, lambda tmp: fig.savefig(tmp, format="png"))


# ----------------------------------------------------------------------------- an invalid map
def write_failure_vtu(path, mesh, igm, extraction=None) -> Path:
    """A VTU of the input tets with their :func:`tet_flags` and the map's singular graph.

    Points: ``igm.mesh.vertices`` (the input's vertices first, in their order and at their input
    positions — the relocation moves some of them in the map's mesh —, then the midpoints of the
    edges the map split, where the map's mesh has them). Cells: the input's tets (``tetra``), cell data per
    flag of :data:`FLAGS` (how many of the tet's sub-tets carry it) and ``flags`` (the bits);
    then the singular edges of the map's mesh (``line``) with ``edge_type`` (1 quarter turn,
    2 half turn, 3 complex), ``valence`` (3, 5; 0 for a half turn, -1 complex) and ``meshable``;
    tet data is -1 on lines and line data -1 on tets. Written atomically.
    """
    import meshio

    fl = tet_flags(igm, extraction, mesh.n_tets)
    X = igm.mesh.vertices.detach().cpu().double().numpy().copy()
    X[: mesh.n_vertices] = mesh.vertices.detach().cpu().double().numpy()
    tets = mesh.tets.cpu().numpy().astype(np.int64)
    lines, ldata = singular_lines(igm)
    T, S = tets.shape[0], lines.shape[0]
    cells = [("tetra", tets)] + ([("line", lines)] if S else [])

    def pair(tet_values, line_values):
        return [tet_values] + ([line_values] if S else [])

    data = {k: pair(v, np.full(S, -1, np.int32)) for k, v in fl["input"].items()}
    data["flags"] = pair(fl["flags_input"], np.full(S, -1, np.int32))
    data.update({k: pair(np.full(T, -1, np.int32), v) for k, v in ldata.items()})
    m = meshio.Mesh(X, cells, cell_data=data)
    return _atomic(path, lambda tmp: meshio.write(str(tmp), m, file_format="vtu"))


_FLAG_COLOURS = {"inverted": "magenta", "degenerate": "darkorange", "unmeshable_singular_edge": "purple",
                 "oversized": "0.45", "cubes_dropped": "gold"}
_EDGE_COLOURS = {3: "tab:blue", 5: "tab:red", 0: "tab:green", -1: "black"}  # valence; 0 half turn, -1 complex
_EDGE_WORDS = {3: "valence 3", 5: "valence 5", 0: "half turn", -1: "complex"}
_PLOT_MAX_POINTS = 20_000


def plot_failure(path_png, mesh, igm, extraction=None, *, verdict_text: str = "", title: str | None = None,
                 where_xyz: dict | None = None) -> Path:
    """A PNG of where a map fails, from two opposite views: the input's boundary (translucent),
    its boundary faces coloured by the flags of their tet, the barycenters of flagged interior
    tets as dots, the map's singular edges coloured by type (valence 3 blue, 5 red, half turn
    green, complex black), and ``where_xyz`` (:attr:`~.validity.MapValidity.where_xyz`: the first
    elements of each failing check) as crosses; the legend counts the flagged input tets and the
    subtitle is ``verdict_text``. matplotlib's Agg canvas; written atomically."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    fl = tet_flags(igm, extraction, mesh.n_tets)
    X = mesh.vertices.detach().cpu().double().numpy()
    bf = mesh.boundary_faces.cpu().numpy().astype(np.int64)
    ft = mesh.face_tets.cpu().numpy()[mesh.boundary_face_index.cpu().numpy()]
    btet = np.where(ft[:, 0] >= 0, ft[:, 0], ft[:, 1])
    flags_in = fl["input"]
    first_flag = np.full(mesh.n_tets, -1)  # the first flag of FLAGS a tet carries (its colour)
    for i, k in reversed(list(enumerate(FLAGS))):
        first_flag[flags_in[k] > 0] = i
    names = list(FLAGS)
    bary = mesh.tet_barycenters.detach().cpu().double().numpy()
    interior = np.ones(mesh.n_tets, bool)
    interior[btet] = False
    lines, ldata = singular_lines(igm)
    Xm = igm.mesh.vertices.detach().cpu().double().numpy()
    lo, hi = X.min(0), X.max(0)
    span = np.maximum(hi - lo, 1e-12 * max(float(np.max(hi - lo)), 1.0))

    fig = Figure(figsize=(13, 7.2), dpi=110)
    FigureCanvasAgg(fig)
    fi, _ = _subsample(bf.shape[0], PLOT_MAX_QUADS)
    tri = X[bf[fi]]
    col = np.tile([0.80, 0.82, 0.86, 0.10], (fi.size, 1))
    flagged = first_flag[btet[fi]] >= 0
    if flagged.any():
        from matplotlib.colors import to_rgba

        col[flagged] = [to_rgba(_FLAG_COLOURS[names[j]], 0.85) for j in first_flag[btet[fi]][flagged]]
    for k, azim in enumerate((-60.0, 120.0)):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(tri, facecolors=col, edgecolors="none"))
        for j, name in enumerate(names):
            sel = np.nonzero(interior & (first_flag == j))[0]
            if sel.size:
                sel = sel[_subsample(sel.size, _PLOT_MAX_POINTS)[0]]
                ax.scatter(*bary[sel].T, s=6, color=_FLAG_COLOURS[name], depthshade=False)
        for v, c in _EDGE_COLOURS.items():
            sel = ldata["valence"] == v
            if sel.any():
                ax.add_collection3d(Line3DCollection(Xm[lines[sel]], colors=c, linewidths=2.0))
        for pts in (where_xyz or {}).values():
            P = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
            ax.scatter(*P.T, marker="x", s=60, color="crimson", depthshade=False)
        ax.set_xlim(lo[0], lo[0] + span[0])
        ax.set_ylim(lo[1], lo[1] + span[1])
        ax.set_zlim(lo[2], lo[2] + span[2])
        ax.set_box_aspect(tuple(span / span.max()))
        ax.view_init(elev=25.0, azim=azim)
        ax.set_axis_off()
        ax.set_title(f"view from azimuth {azim:g}°", fontsize=9)
    handles = [Line2D([], [], color=_FLAG_COLOURS[k], marker="s", lw=0, markersize=9,
                      label=f"{int((flags_in[k] > 0).sum())} tets {FLAGS[k][1]}") for k in names if (flags_in[k] > 0).any()]
    handles += [Line2D([], [], color=c, lw=3, label=f"{int((ldata['valence'] == v).sum())} singular edges, "
                                                     f"{_EDGE_WORDS[v]}")
                for v, c in _EDGE_COLOURS.items() if (ldata["valence"] == v).any()]
    if where_xyz:
        handles.append(Line2D([], [], color="crimson", marker="x", lw=0, markersize=9,
                              label="first elements of each failing check"))
    if not handles:
        handles = [Line2D([], [], color="none", label="no tet flagged, no singular edge")]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 3), frameon=False, fontsize=9,
               title=f"input tets ({mesh.n_tets}) by what fails there (the map lives on {igm.mesh.n_tets} tets: "
                     f"the input refined by its edge splits)", title_fontsize=9)
    lines = ([title] if title else []) + _wrapped(verdict_text)
    fig.suptitle("\n".join(lines), fontsize=10)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.16, top=_top(lines, 7.2), wspace=0.0)
    return _atomic(path_png, lambda tmp: fig.savefig(tmp, format="png"))
