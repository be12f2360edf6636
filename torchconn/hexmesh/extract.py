"""Extraction of a conforming all-hex mesh from an integer-grid map (HEXMESH.md step 8).

Input convention (the map of :mod:`torchconn.hexmesh`):

- ``uvw (T, 4, 3)``: the parameter of local corner ``k`` (vertex ``mesh.tets[t, k]``) of tet ``t``
  in tet ``t``'s chart, dyadic: multiples of ``2**-grid_bits``.
- ``face_rot (F,)`` index into :func:`torchconn.frames.octahedral.group` (identity 0) and
  ``face_shift (F, 3)`` integers: for an interior face ``f`` with ``face_tets[f] = (t0, t1)`` and
  each of its vertices, ``uvw[t1, corner in t1] == G[face_rot[f]] @ uvw[t0, corner in t0] +
  face_shift[f]``. Values on boundary faces are ignored.

Method (all stages vectorized over elements; the walk is a loop over *steps*, not cubes):

1. **Exact input.** Parameters are scaled by ``S = 2**grid_bits`` to int64; every decision below
   is an exact sign (:mod:`torchconn.hexmesh.predicates`). Each tet's parametric orientation is
   computed; tets with ``orient3d <= 0`` (flipped or flat) are unusable, so are tets whose
   bounding box holds more than ``max_tet_points`` lattice points (``oversized``). Every interior
   face is checked against its transition (``seam``), and the holonomy around every edge of a
   face with a non-identity rotation is composed: a singular edge must be a quarter or half turn
   about its own line, and that line an integer line. Tets sharing a vertex with an unusable
   tet, a mismatched face or an invalid singular edge are *tainted* (see ``near_invalid``).
2. **Lattice points.** For every usable tet, the integer points (hex vertices) and the
   half-integer points (cube centres) of its closed image are enumerated from its bounding box
   and classified exactly (inside / on faces).
3. **Stars.** An occurrence ``(t, x)`` lying on face ``k`` of ``t`` is linked to the occurrence of
   the transported point in the neighbour across that face (``G x + s``); the connected
   components (``scipy.sparse.csgraph``) are the points of the parameter domain: one hex vertex
   per integer component, one cube per half-integer component. A component is represented by
   its lowest tet id and its parameter there (``point_tet``, ``point_param``, ``hex_tet``).
4. **Walks.** From each cube centre ``c`` (in its owner tet's chart, the cube's chart) a straight
   walk goes to each of the 8 corners ``c + (+-1/2, +-1/2, +-1/2)`` through tets and across faces,
   carrying the composed transition. The open segment lies inside the open unit cube, which a
   valid map keeps free of singular edges and boundary, so every path inside it reaches the
   same corner. Degenerate passages (through edges and vertices, common on lattice-aligned
   maps) are resolved by Simulation of Simplicity: the start is perturbed to
   ``c + eps (g - c) + eps^2 e_x + eps^3 e_y + eps^4 e_z`` (``g`` the owner tet's centroid), which
   lies inside the owner tet, and the perturbed segment crosses faces only in their interiors;
   the exit face of a tet is decided by the signs of ``q`` against its faces and, when ``q`` is
   beyond two or three of them, by the perturbed side of the planes through the start and the
   shared edges. A walk stops in the first tet whose closed image holds the corner; the corner is
   then the integer component of that occurrence, so cubes that share a corner share the vertex
   (conforming by construction).
5. **Hexes.** A cube whose 8 corners are distinct and whose walks stayed in good tets becomes a
   hex in VTK order (corners ``(0,0,0), (1,0,0), (1,1,0), (0,1,0), (0,0,1), (1,0,1), (1,1,1),
   (0,1,1)`` added to its min corner in the owner tet's chart, which is orientation-preserving).
   Hexes with a quad face shared by three or more hexes, or by two with the same orientation
   (a fold of an invalid map), are dropped as ``overlap``. World positions of hex vertices are
   barycentric interpolation in ``point_tet``.

What is and is not checked: on a valid map every unit cube of the parameter domain becomes one
hex, and neighbouring hexes share their vertices. On an invalid map, each emitted hex's centre
and corners are points of the map joined by straight paths through positively oriented,
untainted tets across exact transitions, and no tet is met under two charts. Hex edges and
faces are not traced (HexEx traces edges), so a cube of an invalid map is still emitted when the
defect lies inside it but away from its 8 walks by more than a ring of tets (possible where tets
are much smaller than hexes), or when a boundary bends inwards between its corners. Every cube is
found once per component of its centre's star: on a broken seam, a centre lying on the seam is
found (and dropped) once from each side.

Drop reasons (:data:`REASONS`, in priority order; a cube gets the first that applies):

- ``flipped_tet``: a walk entered a tet with non-positive parametric volume.
- ``oversized_tet``: a walk entered a tet with more than ``max_tet_points`` lattice points.
- ``seam_mismatch``: a walk crossed an interior face whose corners violate its transition.
- ``near_invalid``: the centre, a corner or a walk lies in a tet that shares a vertex with a
  flipped / flat / oversized tet, a mismatched face or an invalid singular edge (a complex
  singularity, or a singular edge off its integer line): where an invalid map can fold over
  itself, so about two rings of tets around each such element are not trusted. (Why: on
  quantized maps of tetgen balls with flipped and flat tets, extraction without this rule emitted
  hexes with inverted corners next to the folds; with it, none.)
- ``leaves_domain``: a walk crossed a boundary face (a boundary off its integer plane).
- ``walk_limit``: a walk took more than ``max_walk_steps`` steps.
- ``not_closed``: two of the 8 corners are the same vertex, or the walks met one tet under two
  different transitions (the cube wraps around a singularity), or (a guard that seamless faces
  cannot trigger) a point's star holds it at two parameters of one tet.
- ``overlap``: a quad face of the hex is shared by three or more hexes, or by two with the
  same orientation.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from .lattice import _apply, _bad_singular_edges, _bbox, _bbox_counts, _cross_face, _lattice, _stars
from .predicates import _barycentric_signs_int, _orient3d_int, _orient3d_sos_int, to_grid

__all__ = ["extract_hexes", "HexExtraction", "REASONS"]

REASONS = ("flipped_tet", "oversized_tet", "seam_mismatch", "near_invalid", "leaves_domain", "walk_limit",
           "not_closed", "overlap")
_R = {name: i for i, name in enumerate(REASONS)}
_OK = len(REASONS)  # "no reason" sorts after every reason
_CUBE_CHUNK = 1 << 15   # cubes walked together (8 walkers each; bounds the visit records' memory)

#: VTK hexahedron corner offsets from the cube's min corner.
HEX_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                        [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.int64)
#: VTK hexahedron faces, each counter-clockwise seen from outside.
HEX_FACES = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4],
                      [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]], dtype=np.int64)


@dataclass
class HexExtraction:
    """Result of :func:`extract_hexes`.

    Attributes:
        points: ``(N, 3)`` float64 world coordinates of the hex vertices.
        hexes: ``(H, 8)`` int64 VTK-ordered hexes (0-1-2-3 bottom, 4-7 above them), positively
            oriented in parameter space.
        point_tet: ``(N,)`` int64 lowest tet whose closed image holds the vertex.
        point_param: ``(N, 3)`` int64 the vertex's (integer) parameter in ``point_tet``'s chart.
        hex_tet: ``(H,)`` int64 lowest tet whose closed image holds the cube centre (the owner:
            the hex's corners are ``hex_param + HEX_CORNERS`` in its chart).
        hex_param: ``(H, 3)`` int64 min corner of the cube in ``hex_tet``'s chart.
        tet_sign: ``(T,)`` int8 parametric orientation of each tet (``+1`` valid, ``-1`` flipped,
            ``0`` flat).
        oversized_tets: ``(K,)`` int64 positive tets skipped for holding too many lattice points.
        mismatched_faces: ``(M,)`` int64 interior faces whose corners violate their transition.
        invalid_singular_edges: ``(K, 2)`` int64 vertex pairs of interior edges whose holonomy is
            neither the identity nor a quarter/half turn about the edge lying on an integer line.
        dropped_tet, dropped_centre, dropped_reason: ``(D,)`` int64, ``(D, 3)`` float64
            (half-integer centre in ``dropped_tet``'s chart) and ``(D,)`` int8 index into
            :data:`REASONS`: every cube that was found and not emitted.
        timings: seconds per stage (``validate``, ``lattice``, ``stars``, ``walk``, ``assemble``,
            ``total``) and ``walk_steps`` (the most iterations of a batched walk).
    """

    points: np.ndarray
    hexes: np.ndarray
    point_tet: np.ndarray
    point_param: np.ndarray
    hex_tet: np.ndarray
    hex_param: np.ndarray
    tet_sign: np.ndarray
    oversized_tets: np.ndarray
    mismatched_faces: np.ndarray
    invalid_singular_edges: np.ndarray
    dropped_tet: np.ndarray
    dropped_centre: np.ndarray
    dropped_reason: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def dropped(self) -> dict[str, int]:
        """Number of dropped cubes per reason (every reason listed, zeros included)."""
        c = np.bincount(self.dropped_reason.astype(np.int64), minlength=len(REASONS))
        return {name: int(c[i]) for i, name in enumerate(REASONS)}

    def counts(self) -> dict:
        """JSON-ready summary: hexes, points, cubes dropped by reason, flipped/flat tets, faces."""
        return {
            "hexes": int(self.hexes.shape[0]),
            "points": int(self.points.shape[0]),
            "cubes_dropped": int(self.dropped_reason.shape[0]),
            "dropped": self.dropped,
            "flipped_tets": int((self.tet_sign < 0).sum()),
            "flat_tets": int((self.tet_sign == 0).sum()),
            "oversized_tets": int(self.oversized_tets.shape[0]),
            "mismatched_faces": int(self.mismatched_faces.shape[0]),
            "invalid_singular_edges": int(self.invalid_singular_edges.shape[0]),
        }


# ----------------------------------------------------------------------------- group tables
def _group_tables():
    """``(G (24,3,3), mult (24,24), inv (24,))`` of :func:`torchconn.frames.octahedral.group_tables`."""
    from ..frames.octahedral import group_tables

    return group_tables()


# ----------------------------------------------------------------------------- validation
def _few(idx) -> str:
    idx = np.asarray(idx)
    return f"{idx[:8].tolist()}{' ...' if idx.size > 8 else ''} ({idx.size} in all)"


def _np(x, name: str) -> np.ndarray:
    if torch.is_tensor(x):
        return x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except Exception as exc:  # pragma: no cover - exotic input
        raise TypeError(f"{name} must be an array or tensor, got {type(x).__name__}") from exc


def _integral(a: np.ndarray, name: str, what: str) -> np.ndarray:
    if np.issubdtype(a.dtype, np.integer):
        return a.astype(np.int64)
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"{name} must be integer, got {a.dtype}")
    rows = a.reshape(a.shape[0], -1) if a.ndim else a.reshape(1, 1)
    bad = ~np.isfinite(rows) | (rows != np.round(rows))
    if bad.any():
        raise ValueError(f"{name} must be integer-valued; not at {what} {_few(np.nonzero(bad.any(1))[0])}")
    return a.astype(np.int64)


def _validate(mesh, uvw, face_rot, face_shift, grid_bits):
    for attr in ("tets", "faces", "tet_faces", "face_tets", "vertices"):
        if not hasattr(mesh, attr):
            raise TypeError(f"mesh must be a torchconn.TetMesh (no attribute {attr!r}), got {type(mesh).__name__}")
    if isinstance(grid_bits, bool) or not isinstance(grid_bits, (int, np.integer)) or not 1 <= grid_bits <= 40:
        raise ValueError(f"grid_bits must be an integer in [1, 40], got {grid_bits!r}")
    tets = mesh.tets.cpu().numpy().astype(np.int64)
    T, F = tets.shape[0], mesh.faces.shape[0]
    a = _np(uvw, "uvw")
    if a.shape != (T, 4, 3):
        raise ValueError(f"uvw must have shape (T, 4, 3) = ({T}, 4, 3) for this mesh, got {tuple(a.shape)}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise TypeError(f"uvw must be float or integer, got {a.dtype}")
    try:
        U = to_grid(a, grid_bits, name="uvw", limit_bits=52)
    except ValueError as exc:
        raise ValueError(str(exc).replace("at rows", "at tets")) from None
    rot = _np(face_rot, "face_rot")
    if rot.shape != (F,):
        raise ValueError(f"face_rot must have shape (F,) = ({F},), got {tuple(rot.shape)}")
    rot = _integral(rot, "face_rot", "faces")
    shift = _np(face_shift, "face_shift")
    if shift.shape != (F, 3):
        raise ValueError(f"face_shift must have shape (F, 3) = ({F}, 3), got {tuple(shift.shape)}")
    shift = _integral(shift, "face_shift", "faces")
    ft = mesh.face_tets.cpu().numpy().astype(np.int64)
    interior = (ft >= 0).all(1)
    bad = interior & ((rot < 0) | (rot >= 24))
    if bad.any():
        raise ValueError(f"face_rot must index the 24 elements of O (0..23); out of range at faces {_few(np.nonzero(bad)[0])}")
    big = interior & (np.abs(shift).max(1) >= 2 ** (52 - grid_bits))
    if big.any():
        raise ValueError(f"face_shift too large (|shift| * 2**grid_bits must be < 2**52) at faces {_few(np.nonzero(big)[0])}")
    rot = np.where(interior, rot, 0)
    shift = np.where(interior[:, None], shift, 0)
    return tets, U, rot, shift, ft, interior



# ----------------------------------------------------------------------------- walks
def _pair_table():
    """For the 6 pairs of faces ``k1 < k2``: the shared edge ``(i, j)`` and the sign ``r`` of
    ``orient3d(v_k1, v_i, v_j, v_k2)`` for a positive tet (parity of ``(k1, i, j, k2)``)."""
    rows = []
    for k1 in range(4):
        for k2 in range(k1 + 1, 4):
            i, j = sorted({0, 1, 2, 3} - {k1, k2})
            p = [k1, i, j, k2]
            inversions = sum(p[a] > p[b] for a in range(4) for b in range(a + 1, 4))
            rows.append((k1, k2, i, j, 1 if inversions % 2 == 0 else -1))
    return rows


_PAIRS = _pair_table()


def _walk(U, G, mult, inv, tet_faces, ft, face_rot, shiftS, usable, oversized, seam_ok, tainted,
          t0, P, Q, max_steps, bar=None):
    """Batched straight walks from ``P`` (in ``t0``'s chart) to ``Q`` (same chart), scaled int64.

    Returns ``tet (W,)``, ``rot (W,)``, ``shift (W, 3)`` (the final tet and the transform
    ``x_cube = G[rot] x_tet + shift``), ``reason (W,)`` int8 (``_OK`` on success), ``steps``.
    """
    W = t0.size
    cur = t0.copy()
    rot = np.zeros(W, np.int64)
    b = np.zeros((W, 3), np.int64)
    reason = np.full(W, _OK, np.int8)
    touched = tainted[t0].copy()
    P4, Q4 = 4 * P, 4 * Q
    G4 = U[t0].sum(axis=1)                       # 4 x centroid of the start tet (cube chart)
    act = np.arange(W)
    steps = 0
    visits = []                                  # (walker, tet, rot, shift) of every tet entered
    while act.size:
        t = cur[act]
        visits.append((act, t, rot[act], b[act]))
        V = _apply(G, rot[act], U[t]) + b[act][:, None, :]
        s = _barycentric_signs_int(V, Q[act])
        inside = (s >= 0).all(axis=1)
        act, V, s, t = act[~inside], V[~inside], s[~inside], t[~inside]
        if not act.size:
            break
        if steps >= max_steps:
            reason[act] = _R["walk_limit"]
            break
        steps += 1
        beyond = s < 0
        exit_k = np.argmax(beyond, axis=1)
        multi = np.nonzero(beyond.sum(axis=1) >= 2)[0]
        ok = np.ones(act.size, bool)
        if multi.size:
            excluded = np.zeros((multi.size, 4), bool)
            for k1, k2, i, j, r in _PAIRS:
                sel = np.nonzero(beyond[multi, k1] & beyond[multi, k2])[0]
                if not sel.size:
                    continue
                rows = multi[sel]
                w = act[rows]
                sg = _orient3d_sos_int(P4[w], G4[w], 4 * V[rows, i], 4 * V[rows, j], Q4[w])
                excluded[sel, k2] |= sg == r
                excluded[sel, k1] |= sg == -r
                excluded[sel[sg == 0]] = True   # impossible for a positive tet: flag, never guess
            cand = beyond[multi] & ~excluded
            ok[multi] = cand.sum(axis=1) == 1
            exit_k[multi] = np.argmax(cand, axis=1)
        f = tet_faces[t, exit_k]
        pair = ft[f]
        from_t0 = pair[:, 0] == t
        nbr = np.where(from_t0, pair[:, 1], pair[:, 0])
        code = np.full(act.size, _OK, np.int8)
        code[~ok] = _R["not_closed"]
        n0 = np.maximum(nbr, 0)
        code[(code == _OK) & (nbr < 0)] = _R["leaves_domain"]
        code[(code == _OK) & ~usable[n0] & oversized[n0]] = _R["oversized_tet"]
        code[(code == _OK) & ~usable[n0]] = _R["flipped_tet"]
        code[(code == _OK) & ~seam_ok[f]] = _R["seam_mismatch"]
        fail = code != _OK
        reason[act[fail]] = code[fail]
        go = ~fail
        w, f, from_t0, nbr = act[go], f[go], from_t0[go], nbr[go]
        rot[w], b[w] = _cross_face(G, mult, inv, rot[w], b[w], face_rot[f], shiftS[f], from_t0)
        cur[w] = nbr
        touched[w] |= tainted[nbr]
        act = w
        if bar is not None:
            bar.set_postfix(walk_step=steps, active=int(act.size))
    near = (reason == _OK) & touched
    reason[near] = _R["near_invalid"]
    visits = tuple(np.concatenate(x) for x in zip(*visits)) if visits else None
    return cur, rot, b, reason, steps, visits


def _chart_conflicts(visits, n_cubes: int) -> np.ndarray:
    """``(C,)`` bool: cubes whose walks met one tet under two different transforms (the cube
    wraps around a singularity of an invalid map; in a valid map the open cube unfolds uniquely)."""
    out = np.zeros(n_cubes, bool)
    if visits is None:
        return out
    w, t, rot, b = visits
    cube = w // 8
    order = np.lexsort((b[:, 2], b[:, 1], b[:, 0], rot, t, cube))
    cube, t, rot, b = cube[order], t[order], rot[order], b[order]
    same_tet = (cube[1:] == cube[:-1]) & (t[1:] == t[:-1])
    differ = (rot[1:] != rot[:-1]) | (b[1:] != b[:-1]).any(axis=1)
    out[cube[1:][same_tet & differ]] = True
    return out


# ----------------------------------------------------------------------------- main entry
def extract_hexes(mesh, uvw, face_rot, face_shift, *, grid_bits: int = 20, progress: bool = False,
                  max_walk_steps: int = 4096, max_tet_points: int = 1 << 22) -> HexExtraction:
    """Extract the hexes of an integer-grid map (HexEx-style, exact; see the module docstring).

    Args:
        mesh: :class:`torchconn.TetMesh` (``tets`` positively oriented in 3D).
        uvw: ``(T, 4, 3)`` float64 (or integer) array or tensor, the parameter of local corner ``k``
            of tet ``t`` in tet ``t``'s chart, multiples of ``2**-grid_bits`` with
            ``|uvw| * 2**grid_bits < 2**52``.
        face_rot: ``(F,)`` int index into :func:`torchconn.frames.octahedral.group`.
        face_shift: ``(F, 3)`` int; for an interior face with ``face_tets[f] = (t0, t1)``,
            ``uvw_t1 = G[face_rot[f]] uvw_t0 + face_shift[f]`` at its three vertices. Boundary
            faces are ignored.
        grid_bits: the dyadic grid ``2**-grid_bits`` of ``uvw`` (1..40).
        progress: a tqdm bar over the stages (a warning and no bar without tqdm).
        max_walk_steps: walks longer than this are dropped (``walk_limit``).
        max_tet_points: usable tets whose bounding box holds more lattice points than this are
            skipped (``oversized_tet``: memory stays bounded on broken maps).

    Returns:
        :class:`HexExtraction`. Invalid maps (flipped tets, boundaries off their planes, broken
        seams) are extracted where possible; what was dropped and why is in ``dropped*``.

    Raises:
        TypeError / ValueError: a mesh that is not a TetMesh, arrays of the wrong shape, ``uvw``
            off the ``2**-grid_bits`` grid or too large (naming the tets), ``face_rot`` outside
            0..23 or non-integer ``face_shift`` on interior faces (naming the faces).

    Cost (numpy, one core; 2026-11-25, measured under a load of ~5 on 2 cores): about 0.6 CPU s
    per 10k hexes when the tets are about the size of the hexes (6 tets per hex) and 1.7 s with 48
    tets per hex (longer walks); per-stage seconds are in ``timings``.
    """
    timings: dict = {}
    t_start = time.perf_counter()
    bar = _bar(progress)
    tets, U, face_rot, face_shift, ft, interior = _validate(mesh, uvw, face_rot, face_shift, grid_bits)
    grid_bits = int(grid_bits)
    S = 1 << grid_bits
    G, mult, inv = _group_tables()
    tet_faces = mesh.tet_faces.cpu().numpy().astype(np.int64)
    faces = mesh.faces.cpu().numpy().astype(np.int64)
    verts = mesh.vertices.detach().cpu().numpy().astype(np.float64)
    shiftS = face_shift * S

    # orientation, oversized tets, seams, taint
    tet_sign = _orient3d_int(U[:, 0], U[:, 1], U[:, 2], U[:, 3])
    bbox = _bbox(U)
    n_int = _bbox_counts(bbox, grid_bits, 0)[2]
    n_half = _bbox_counts(bbox, grid_bits, S // 2)[2]
    oversized = (tet_sign > 0) & (np.maximum(n_int, n_half) > max_tet_points)
    usable = (tet_sign > 0) & ~oversized
    seam_ok = np.ones(faces.shape[0], bool)
    fi = np.nonzero(interior)[0]
    if fi.size:
        t0f, t1f = ft[fi, 0], ft[fi, 1]
        fv = faces[fi]
        loc0 = (tets[t0f][:, None, :] == fv[:, :, None]).argmax(axis=2)
        loc1 = (tets[t1f][:, None, :] == fv[:, :, None]).argmax(axis=2)
        U0 = U[t0f[:, None], loc0]                     # (n, 3, 3): the face's corners in t0, t1
        U1 = U[t1f[:, None], loc1]
        seam_ok[fi] = (_apply(G, face_rot[fi], U0) + shiftS[fi][:, None, :] == U1).all(axis=(1, 2))
    mismatched = interior & ~seam_ok
    face_good = interior & seam_ok & usable[np.maximum(ft[:, 0], 0)] & usable[np.maximum(ft[:, 1], 0)]
    bad_edges = _bad_singular_edges(tets, mesh.tet_edges.cpu().numpy().astype(np.int64), tet_faces, ft,
                                    mesh.face_edges.cpu().numpy().astype(np.int64), U, G, mult, inv, face_rot,
                                    shiftS, usable, seam_ok, S)
    bad_vertex = np.zeros(verts.shape[0], bool)
    bad_vertex[tets[~usable].ravel()] = True
    bad_vertex[faces[mismatched].ravel()] = True
    bad_vertex[bad_edges.ravel()] = True
    tainted = usable & bad_vertex[tets].any(axis=1)
    timings["validate"] = time.perf_counter() - t_start
    _step(bar, "lattice")

    t1 = time.perf_counter()
    vlat = _lattice(U, bbox, usable, grid_bits, half=False)
    clat = _lattice(U, bbox, usable, grid_bits, half=True)
    timings["lattice"] = time.perf_counter() - t1
    _step(bar, "stars")

    t1 = time.perf_counter()
    vlabel, vrep, vbroken, vmulti = _stars(vlat, grid_bits, G, inv, tet_faces, ft, face_good, face_rot, shiftS, tainted)
    _, crep, cbroken, cmulti = _stars(clat, grid_bits, G, inv, tet_faces, ft, face_good, face_rot, shiftS, tainted)
    timings["stars"] = time.perf_counter() - t1
    _step(bar, "walk")

    # one cube per centre component, owned by its lowest tet; 8 walks each
    t1 = time.perf_counter()
    C = crep.size
    own = clat.tet[crep]
    kc = clat.k[crep]                               # centre = kc + 1/2 in own's chart
    reason = np.full(C, _OK, np.int8)
    reason = np.minimum(reason, np.where(cbroken, _R["near_invalid"], _OK).astype(np.int8))
    reason = np.minimum(reason, np.where(cmulti, _R["not_closed"], _OK).astype(np.int8))
    wt0 = np.repeat(own, 8)
    wQ = ((kc[:, None, :] + HEX_CORNERS[None]) * S).reshape(-1, 3)   # the 8 integer corners, scaled
    wtet, wrot = np.empty_like(wt0), np.empty_like(wt0)
    wb, wreason = np.empty_like(wQ), np.empty(wt0.size, np.int8)
    wraps = np.zeros(C, bool)
    steps = 0
    for c0 in range(0, C, _CUBE_CHUNK):             # chunks bound the memory of the visit records
        cs = slice(c0, min(C, c0 + _CUBE_CHUNK))
        ws = slice(8 * cs.start, 8 * cs.stop)
        P = np.repeat(kc[cs] * S + S // 2, 8, axis=0)
        wtet[ws], wrot[ws], wb[ws], wreason[ws], n, visits = _walk(
            U, G, mult, inv, tet_faces, ft, face_rot, shiftS, usable, oversized, seam_ok, tainted,
            wt0[ws], P, wQ[ws], max_walk_steps, bar)
        wraps[cs] = _chart_conflicts(visits, cs.stop - cs.start)
        steps = max(steps, n)
    timings["walk"] = time.perf_counter() - t1
    timings["walk_steps"] = steps
    _step(bar, "assemble")

    # corners -> vertex components
    t1 = time.perf_counter()
    done = wreason == _OK
    corner_v = np.full(wt0.size, -1, np.int64)
    wi = np.nonzero(done)[0]
    if wi.size:
        q_t = _apply(G, inv[wrot[wi]], wQ[wi] - wb[wi])        # corner in the final tet's chart
        occ = vlat.lookup(wtet[wi], q_t >> grid_bits)
        lost = occ < 0                                          # cannot happen: the tet holds it
        wreason[wi[lost]] = _R["not_closed"]
        found = wi[~lost]
        lab = vlabel[occ[~lost]]
        corner_v[found] = lab
        wreason[found[vmulti[lab]]] = _R["not_closed"]
        wreason[found[vbroken[lab] & (wreason[found] == _OK)]] = _R["near_invalid"]
    reason = np.minimum(reason, wreason.reshape(C, 8).min(axis=1))
    reason[wraps & (reason == _OK)] = _R["not_closed"]
    hv = corner_v.reshape(C, 8)
    srt = np.sort(hv, axis=1)
    repeated = (srt[:, 1:] == srt[:, :-1]).any(axis=1) & (reason == _OK)
    reason[repeated] = _R["not_closed"]
    reason = _drop_overlaps(hv, reason)

    keep = np.nonzero(reason == _OK)[0]
    keep = keep[np.lexsort((kc[keep, 2], kc[keep, 1], kc[keep, 0], own[keep]))]
    hexes_v = hv[keep]
    used, inverse = np.unique(hexes_v.ravel(), return_inverse=True)
    rep_occ = vrep[used]
    p_tet = vlat.tet[rep_occ]
    p_param = vlat.k[rep_occ]
    order = np.lexsort((p_param[:, 2], p_param[:, 1], p_param[:, 0], p_tet))
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    hexes = rank[inverse].reshape(-1, 8).astype(np.int64)
    p_tet, p_param = p_tet[order], p_param[order]
    points = _world(verts, tets, U, p_tet, p_param * S)

    dropped = np.nonzero(reason != _OK)[0]
    dropped = dropped[np.lexsort((kc[dropped, 2], kc[dropped, 1], kc[dropped, 0], own[dropped]))]
    timings["assemble"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t_start
    if bar is not None:
        bar.update(1)
        bar.close()
    return HexExtraction(
        points=points, hexes=hexes, point_tet=p_tet.astype(np.int64), point_param=p_param.astype(np.int64),
        hex_tet=own[keep].astype(np.int64), hex_param=kc[keep].astype(np.int64), tet_sign=tet_sign,
        oversized_tets=np.nonzero(oversized)[0].astype(np.int64),
        mismatched_faces=np.nonzero(mismatched)[0].astype(np.int64),
        invalid_singular_edges=bad_edges.astype(np.int64),
        dropped_tet=own[dropped].astype(np.int64), dropped_centre=kc[dropped].astype(np.float64) + 0.5,
        dropped_reason=reason[dropped].astype(np.int8), timings=timings)


def _drop_overlaps(hv: np.ndarray, reason: np.ndarray) -> np.ndarray:
    """Mark ``overlap`` on candidate hexes (``reason == _OK``) with a quad face shared by three or
    more candidates, or by two with the same orientation (a fold)."""
    cand = np.nonzero(reason == _OK)[0]
    if not cand.size:
        return reason
    quads = hv[cand][:, HEX_FACES].reshape(-1, 4)          # (6n, 4) oriented
    owner = np.repeat(cand, 6)
    key = np.sort(quads, axis=1)
    # orientation of a quad: rotate its smallest vertex first, compare the two neighbours
    m = np.argmin(quads, axis=1)
    nxt = quads[np.arange(quads.shape[0]), (m + 1) % 4]
    prv = quads[np.arange(quads.shape[0]), (m + 3) % 4]
    orient = nxt < prv
    _, inv_, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv_ = inv_.ravel()
    bad = cnt[inv_] > 2
    two = cnt[inv_] == 2
    n_true = np.bincount(inv_, weights=orient.astype(np.float64), minlength=cnt.size)
    same = two & ((n_true[inv_] == 0) | (n_true[inv_] == 2))
    out = reason.copy()
    hit = np.unique(owner[bad | same])
    out[hit] = _R["overlap"]
    return out


def _world(verts, tets, U, p_tet, Q) -> np.ndarray:
    """World position of scaled parameter ``Q (N, 3)`` in tet ``p_tet (N,)`` by barycentric
    interpolation (float64; the barycentric coordinates are ratios of exact-input determinants)."""
    if p_tet.size == 0:
        return np.zeros((0, 3), np.float64)
    V = U[p_tet].astype(np.float64) - Q.astype(np.float64)[:, None, :]   # relative to the point
    def det(a, b, c):
        return np.einsum("ni,ni->n", a, np.cross(b, c))
    v0, v1, v2, v3 = V[:, 0], V[:, 1], V[:, 2], V[:, 3]
    # lambda_k = vol(tet with vertex k replaced by the point (origin)) / vol(tet)
    l0 = det(v1, v2, v3)                             # orient3d(q, v1, v2, v3) with q at the origin
    l1 = -det(v0, v2, v3)
    l2 = det(v0, v1, v3)
    l3 = -det(v0, v1, v2)
    lam = np.stack([l0, l1, l2, l3], axis=1)
    lam /= lam.sum(axis=1, keepdims=True)
    return np.einsum("nk,nki->ni", lam, verts[tets[p_tet]])


def _bar(progress: bool):
    if not progress:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        warnings.warn("extract_hexes(progress=True): tqdm is not installed (pip install tqdm); no progress bar",
                      stacklevel=3)
        return None
    return tqdm(total=5, desc="extract_hexes: validate", dynamic_ncols=True)


def _step(bar, stage: str) -> None:
    if bar is not None:
        bar.update(1)
        bar.set_description(f"extract_hexes: {stage}")
