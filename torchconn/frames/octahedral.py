"""The octahedral rotation group O (24 rotations of the cube), frame matching, matched holonomy.

Conventions
-----------
* A *frame* is a rotation ``F (3, 3)`` whose columns are its three axes in world coordinates:
  ``frames[i][:, k]`` is axis ``k`` of the frame at vertex ``i``. An octahedral (cross) frame is
  the class ``{F g : g in O}``: right-multiplying by ``g`` permutes the axes with signs.
* Matching (the discrete "period jump"): for frames ``F_i, F_j`` the best match is
  ``g*_ij = argmin_{g in O} ||F_i g - F_j||_F = argmax_{g in O} tr(g^T F_i^T F_j)``, so that
  ``F_i g*_ij ~ F_j``. For canonical edges ``(i, j)``, ``i < j``, the reverse match is defined as
  ``g*_ji = g*_ij^T`` (computed once, transposed), so loops are consistent.
* Matched holonomy of a face ``[a < b < c]`` is ``g_ab g_bc g_ca``; it is the identity for a
  regular face and a non-trivial element of O around a singular curve (e.g. Nieser et al. 2011,
  Ray et al. 2016). Since it is an exact group element it is compared with the identity
  exactly (entries differ by 1 or 2), no tolerance is involved.
* Per-tet frames (:func:`tet_frames`): tet ``t`` with lowest-index vertex ``a`` takes
  the chordal mean of its four vertex frames relabeled into the frame of ``a`` along the tet's
  edges, ``M = (1/4) sum_v F_v g*_av^T`` (``g*_aa = I``), projected to SO(3):
  ``tet_frames[t] = F_a polar(F_a^T M)`` (``= polar(M)``; written about ``F_a`` so that a tet whose
  relabeled frames agree returns exactly ``F_a``). So ``tet_frames[t]`` carries the axis labels of
  ``F_a``, and ``tet_frames[t] g*_av ~ F_v`` for the tet's other vertices.
"""
from __future__ import annotations

import itertools

import torch

from ..lie import so3

__all__ = [
    "group",
    "group_tables",
    "match",
    "match_edges",
    "closest_element",
    "matched_rotations",
    "face_matched_holonomy",
    "singular_faces",
    "tets_with_one_singular_face",
    "tet_relabeling",
    "tet_frames",
]


def _group_list() -> list[list[list[int]]]:
    """The 24 signed permutation matrices with determinant +1, identity first (pure Python)."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            M = [[0] * 3 for _ in range(3)]
            for col, row in enumerate(perm):
                M[row][col] = signs[col]
            det = (
                M[0][0] * (M[1][1] * M[2][2] - M[1][2] * M[2][1])
                - M[0][1] * (M[1][0] * M[2][2] - M[1][2] * M[2][0])
                + M[0][2] * (M[1][0] * M[2][1] - M[1][1] * M[2][0])
            )
            if det == 1:
                mats.append(M)
    return mats  # permutations() starts with (0,1,2) and signs with (1,1,1): identity first


_GROUP = _group_list()


def group(dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> torch.Tensor:
    """The rotation group O of the cube as a ``(24, 3, 3)`` tensor, identity first.

    Invariants (mirrored in ``tests/test_octahedral.py``): 24 distinct signed permutation
    matrices, ``det = +1``, closed under products and transposes.
    """
    return torch.tensor(_GROUP, dtype=dtype or torch.get_default_dtype(), device=device)


def group_tables():
    """Integer tables of O for combinatorial code: ``(G, mul, inv)`` numpy int64 arrays,
    ``G (24, 3, 3)`` the elements (the order of :func:`group`), ``mul (24, 24)`` with
    ``G[mul[i, j]] = G[i] @ G[j]`` and ``inv (24,)`` with ``G[inv[i]] = G[i]^T`` (built once, cached;
    read-only)."""
    global _TABLES
    if _TABLES is None:
        import numpy as np

        G = np.array(_GROUP, dtype=np.int64)
        key = {tuple(r): i for i, r in enumerate(G.reshape(24, 9).tolist())}
        prod = np.einsum("aij,bjk->abik", G, G).reshape(24 * 24, 9)
        mul = np.array([key[tuple(r)] for r in prod.tolist()], dtype=np.int64).reshape(24, 24)
        inv = np.array([key[tuple(g.T.reshape(-1).tolist())] for g in G], dtype=np.int64)
        for a in (G, mul, inv):
            a.setflags(write=False)
        _TABLES = (G, mul, inv)
    return _TABLES


_TABLES = None


def _check_mats(name: str, M: torch.Tensor) -> None:
    if not torch.is_tensor(M) or M.shape[-2:] != (3, 3):
        shape = tuple(M.shape) if torch.is_tensor(M) else type(M).__name__
        raise ValueError(f"{name} must be a tensor of shape (..., 3, 3), got {shape}")
    if not M.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor, got {M.dtype}")


def match(F_i: torch.Tensor, F_j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Best matching element ``g* = argmax_{g in O} tr(g^T F_i^T F_j)``, batched.

    Args:
        F_i, F_j: ``(..., 3, 3)`` frames (broadcastable).

    Returns:
        ``index (...)`` long into :func:`group` and ``g (..., 3, 3)`` the matching element, so that
        ``F_i @ g ~ F_j``. Ties go to the lowest index (deterministic).

    Invariance: ``match(F_i h, F_j)`` returns ``h^T g*`` for ``h in O`` (the same matched frame
    ``F_i g*``).
    """
    _check_mats("F_i", F_i)
    _check_mats("F_j", F_j)
    return _best_element(F_i.transpose(-1, -2) @ F_j)


def _best_element(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``argmax_{g in O} tr(g^T M)`` for ``M (..., 3, 3)``: ``(index (...), g (..., 3, 3))``.

    ``tr(g^T M) = sum_ab g_ab M_ab``: one ``(N, 9) x (9, 24)`` product against the flattened
    group (a single GEMM; on CPU it is cheaper than 24 signed 3-entry sums of strided columns or
    an index-table gather, measured at 10^6 edges), then ``max`` over the 24 scores, which
    returns the first maximal index (lowest index on ties, like ``argmax``, and faster than it on
    CPU). The element is a row ``index_select`` from the flattened ``(24, 9)`` group table.
    """
    G = group(M.dtype, M.device)
    batch = M.shape[:-2]
    scores = M.reshape(-1, 9) @ G.reshape(24, 9).t()  # (N, 24)
    idx = scores.max(-1).indices
    g = G.reshape(24, 9).index_select(0, idx).reshape(*batch, 3, 3)
    return idx.reshape(batch), g


def closest_element(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest element of O to ``R (..., 3, 3)`` in the Frobenius norm.

    Returns ``(index (...), g (..., 3, 3))``; equals ``match(I, R)``.
    """
    _check_mats("R", R)
    return _best_element(R)  # match(I, R): I^T R = R, no product needed


def _check_frames(frames: torch.Tensor) -> None:
    if not torch.is_tensor(frames) or frames.dim() != 3 or frames.shape[-2:] != (3, 3):
        shape = tuple(frames.shape) if torch.is_tensor(frames) else type(frames).__name__
        raise ValueError(f"frames must be a (V, 3, 3) tensor, got {shape}")


def _check_index(name: str, idx: torch.Tensor, width: int, V: int) -> None:
    if not torch.is_tensor(idx) or idx.dim() != 2 or idx.shape[1] != width:
        shape = tuple(idx.shape) if torch.is_tensor(idx) else type(idx).__name__
        raise ValueError(f"{name} must be an integer tensor of shape (N, {width}), got {shape}")
    if idx.is_floating_point():
        raise TypeError(f"{name} must be an integer tensor, got {idx.dtype}")
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= V):
        raise IndexError(f"{name} refers to vertices outside [0, {V}) (frames has {V} rows)")


def match_edges(frames: torch.Tensor, edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Best match of every edge, ``frames[i] @ g*_ij ~ frames[j]`` for the rows ``(i, j)`` of ``edges``.

    The one edge-matching convention of the package: the first endpoint's frame is relabeled
    onto the second's. The reverse direction is the transpose, ``g*_ji = g*_ij^T`` (up to exact
    ties, which go to the lowest index of :func:`group` in each direction).

    Args:
        frames: ``(V, 3, 3)``; ``frames[i][:, k]`` is axis ``k`` at vertex ``i`` (world coords).
        edges: ``(E, 2)`` long, row ``(i, j)`` (no range check: hot paths call this every step).

    Returns:
        ``(index (E,) long into group(), g (E, 3, 3))`` as :func:`match` of
        ``frames[edges[:, 0]]`` against ``frames[edges[:, 1]]``.
    """
    return match(frames.index_select(0, edges[:, 0]), frames.index_select(0, edges[:, 1]))


def matched_rotations(frames: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Per-edge matching ``g*_ij (E, 3, 3)`` with ``frames[i] @ g*_ij ~ frames[j]``.

    Args:
        frames: ``(V, 3, 3)``; ``frames[i][:, k]`` is axis ``k`` at vertex ``i`` (world coords).
        edges: ``(E, 2)`` long, row ``(i, j)``.
    """
    _check_frames(frames)
    _check_index("edges", edges, 2, frames.shape[0])
    return match_edges(frames, edges)[1]


def _faces_of(faces_or_mesh) -> torch.Tensor:
    faces = getattr(faces_or_mesh, "faces", faces_or_mesh)
    if not torch.is_tensor(faces):
        raise TypeError(f"expected a (F, 3) face tensor or a mesh with .faces, got {type(faces_or_mesh).__name__}")
    return faces


def face_matched_holonomy(frames: torch.Tensor, faces_or_mesh) -> torch.Tensor:
    """Matched holonomy ``g_ab g_bc g_ca (F, 3, 3)`` of faces ``[a, b, c]``.

    Each pair is matched in ascending vertex order and transposed when traversed the other way
    (``g_ji = g_ij^T``), so the result agrees with :func:`matched_rotations` on the mesh's
    canonical edges. Faces given in any vertex order; for the canonical sorted faces
    ``[a < b < c]`` the product is ``g_ab g_bc g_ac^T``.

    Args:
        frames: ``(V, 3, 3)``.
        faces_or_mesh: ``(F, 3)`` long, or a mesh whose ``.faces`` is used.
    """
    faces = _faces_of(faces_or_mesh)
    _check_frames(frames)
    _check_index("faces", faces, 3, frames.shape[0])

    def oriented(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        lo, hi = torch.minimum(u, v), torch.maximum(u, v)
        g = match_edges(frames, torch.stack([lo, hi], 1))[1]
        return torch.where((u < v)[:, None, None], g, g.transpose(-1, -2))

    a, b, c = faces.unbind(-1)
    return oriented(a, b) @ oriented(b, c) @ oriented(c, a)


def singular_faces(frames: torch.Tensor, mesh) -> tuple[torch.Tensor, torch.Tensor]:
    """Faces whose matched holonomy is not the identity.

    Args:
        frames: ``(V, 3, 3)``.
        mesh: a ``TetMesh`` (uses ``mesh.faces``) or a ``(F, 3)`` face tensor.

    Returns:
        ``mask (F,) bool`` and ``faces[mask] (S, 3)``.
    """
    faces = _faces_of(mesh)
    H = face_matched_holonomy(frames, faces)
    eye = torch.eye(3, dtype=H.dtype, device=H.device)
    # H is an exact signed permutation: any entry off the identity differs by >= 1
    mask = ((H - eye).abs() > 0.5).flatten(-2).any(-1)
    return mask, faces[mask]


def tets_with_one_singular_face(mask: torch.Tensor, mesh) -> torch.Tensor:
    """``(T,) bool``: tets with exactly one singular face (a singular curve that ends inside a
    tet, which a valid frame field for hex meshing never has).

    Args:
        mask: ``(F,) bool`` from :func:`singular_faces`.
        mesh: a ``TetMesh`` (uses ``mesh.tet_faces (T, 4)``) or a ``(T, 4)`` tensor of face ids.
    """
    tet_faces = getattr(mesh, "tet_faces", mesh)
    if not torch.is_tensor(tet_faces) or tet_faces.dim() != 2 or tet_faces.shape[1] != 4:
        raise ValueError("mesh must be a TetMesh or a (T, 4) tensor of face indices")
    if mask.dtype != torch.bool or mask.dim() != 1:
        raise ValueError(f"mask must be a 1-D bool tensor, got {mask.dtype} {tuple(mask.shape)}")
    if tet_faces.numel() and int(tet_faces.max()) >= mask.shape[0]:
        raise IndexError(f"tet_faces refers to face {int(tet_faces.max())} but mask has {mask.shape[0]} faces")
    return mask[tet_faces].sum(-1) == 1


# ----------------------------------------------------------------------------- per-tet frames
def tet_relabeling(mesh, matchings: torch.Tensor, dtype: torch.dtype | None = None):
    """The relabeling of the rule of :func:`tet_frames`: ``(a (T,), others (T, 3), g (T, 3, 3, 3))``,
    each tet's lowest vertex ``a``, its other three vertices (all ``> a``) and the matchings ``g`` of
    the edges ``(a, v)`` (``F_a g ~ F_v``) from the edge ``matchings (E,)`` of :func:`match_edges`;
    ``g`` in ``dtype``, on the mesh's device."""
    tets = mesh.tets
    a = tets.min(dim=1).values
    others = tets.sort(dim=1).values[:, 1:]
    eid, _ = mesh.edge_index(a[:, None].expand_as(others), others)
    return a, others, group(dtype, tets.device)[matchings[eid]]


def tet_frames(frames: torch.Tensor, mesh, matchings: torch.Tensor | None = None) -> torch.Tensor:
    """Per-tet frames ``(T, 3, 3)`` from per-vertex ``frames (V, 3, 3)`` (rule: module docstring).

    Args:
        frames: ``(V, 3, 3)`` rotations, ``frames[i][:, k]`` axis ``k`` at vertex ``i``.
        mesh: ``TetMesh`` (``tets``, ``edges``, ``edge_index``).
        matchings: ``(E,)`` indices of :func:`match_edges` on ``mesh.edges`` (computed when ``None``).

    Returns:
        ``(T, 3, 3)`` rotations; ``tet_frames[t]`` has the axis labels of the frame of the tet's
        lowest-index vertex ``a``, and equals ``frames[a]`` exactly where the four relabeled frames do.
    """
    if matchings is None:
        matchings = match_edges(frames, mesh.edges)[0]
    a, others, g = tet_relabeling(mesh, matchings, frames.dtype)
    Fa = frames[a]
    relabeled = frames[others] @ g.transpose(-1, -2)  # F_v g^T ~ F_a
    # mean of the deviations from F_a; where they all vanish the tet takes F_a itself (no SVD round-off)
    dev = (relabeled - Fa[:, None]).sum(1) / 4.0
    exact = (dev == 0).flatten(-2).all(-1)
    eye = torch.eye(3, dtype=frames.dtype, device=frames.device)
    P = so3.project_to_rotation(torch.where(exact[:, None, None], eye, Fa.transpose(-1, -2) @ (Fa + dev)))
    return torch.where(exact[:, None, None], Fa, Fa @ P)
