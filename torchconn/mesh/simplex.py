"""Local combinatorics of a simplex with vertex labels ``0..s-1`` (one home for the templates).

- Local pair order is lexicographic: ``(0,1), (0,2), ..., (0,s-1), (1,2), ..., (s-2,s-1)``
  (:func:`pair_list`); for a tet ``01, 02, 03, 12, 13, 23``, the order of ``TetMesh.tet_edges``.
- Face ``k`` of a tet is opposite local vertex ``k``, vertices ascending (:data:`TET_FACES`),
  with coefficient ``(-1)^k`` in ``∂[0123] = [123] - [023] + [013] - [012]``
  (:data:`TET_FACE_SIGNS`).
- Slot ``m`` of a triangle ``[p<q<r]`` is its edge opposite the ``m``-th vertex
  (``qr, pr, pq``), with coefficient ``(-1)^m`` in ``∂[pqr] = [qr] - [pr] + [pq]``
  (:data:`FACE_EDGE_SIGNS`).
"""
from __future__ import annotations

import itertools
from functools import lru_cache

__all__ = ["pair_list", "TET_FACES", "TET_FACE_SIGNS", "FACE_EDGE_SIGNS"]

#: Local faces of a tet: face ``k`` is opposite local vertex ``k``, vertices ascending.
TET_FACES = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
#: Incidence of face ``k`` in ``∂[0123] = [123] - [023] + [013] - [012]``.
TET_FACE_SIGNS = (1, -1, 1, -1)
#: Incidence of the edge opposite slot ``m`` of ``[p<q<r]`` in ``∂[pqr] = [qr] - [pr] + [pq]``.
FACE_EDGE_SIGNS = (1, -1, 1)


@lru_cache(maxsize=None)
def pair_list(s: int) -> tuple[tuple[int, int], ...]:
    """Lexicographic list of local vertex pairs ``(i, j)``, ``i < j < s``."""
    return tuple(itertools.combinations(range(s), 2))
