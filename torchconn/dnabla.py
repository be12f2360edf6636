"""Covariant exterior derivatives of discrete bundle-valued forms (report Chs. 4 and 5).

Representation (dense forms on a simplex template)
--------------------------------------------------
Everything here works per simplex with *local* vertex labels ``0..s-1`` and is batched over any
leading dims (one simplex per batch entry, e.g. all tets of a mesh at once).

* Transports: ``T (..., s, s, n, n)`` with ``T[..., i, j] = R_{x_i x_j}`` (fiber at ``x_j`` ->
  fiber at ``x_i``; identity on the diagonal), as built by
  :func:`torchconn.transport.dense_simplex_transports`.
* A discrete **vector-valued k-form** restricted to the simplex is a dense tensor over *ordered*
  ``(k+1)``-tuples of labels, ``alpha (..., s, ..(k+1 times).., s, n)``: the value
  ``alpha[..., i0, .., ik, :] = α[x_i0 .. x_ik]`` lives in the fiber of the first label
  ``x_i0``. Entries with repeated labels are carried along but never influence an entry with
  distinct labels. With ``matrix_values=True`` the values are ``(n, m)`` matrices whose columns
  are vectors in the fiber of the first label (how the connection 1-form ``w_ij = R_ij - I`` is
  differentiated as a vector-valued form, Remark 2.2 / Ch. 5).
* A **Lie-algebra (endomorphism) valued k-form** has values ``(n, n)``:
  ``beta[..., i0, .., ik, :, :] = ⟨β,[x_i0..x_ik]⟩_{x_i0}^{x_ik}`` maps the fiber at the *cut*
  vertex (last label) to the fiber at the *evaluation* vertex (first label); a gauge change
  ``G`` acts as ``G_{i0} X G_{ik}^T``.
* The number of label dims (hence ``k``) is inferred from the ndim difference between the form
  and ``T``: both must have the same number of leading batch dims (broadcastable).
* Every operator can be evaluated on all ordered tuples (``tuples=None``, dense output over
  ``s^(k+2)`` resp. ``s^(k+1)`` tuples) or on an explicit ``(M, m)`` long table of label tuples
  (output ``(..., M, value)``). Any operator also accepts a :class:`ListForm` (values on a
  list of tuples) as input, so chains touch only the entries they read: the tet wrappers
  evaluate ``𝔡∇ Alt 𝔡∇ Alt θ̃`` through 12 pairs, 24 triples and 4 faces, never the dense
  ``4^4`` table. The only Python loops are over the few tuples/permutations of the template.

Operators (CONVENTIONS §1, errata 1, 2, 4, 5, 6, 8)
---------------------------------------------------
* :func:`unsymmetrized_vector` -- corrected Def. 5.1, vector version:
  ``⟨𝔡∇α,[x0..x(k+1)]⟩ = R_{x0x1} α[x1..x(k+1)] + Σ_{j=1}^{k+1} (-1)^j α[s \\ x_j]``.
  This is *the same formula* as the BEHS21 / Sch18 covariant derivative quoted at the start of
  Ch. 4 (``R_ab α[bcd]_b + Σ_i (-1)^i α[a..î..d]_a``); :func:`behs21` is that operator applied to
  a plain (non-alternated) form, e.g. θ, where twice it gives ``(R_ab R_bc - R_ac) θ_cd``.
* :func:`unsymmetrized_lie` -- corrected Def. 5.1, Lie version (erratum 2), evaluation ``x0``,
  cut ``x(k+1)``.
* :func:`alt_vector`, :func:`alt_lie` -- Alt of Def. 5.2 with ``1/(k+1)!`` (erratum 8), and the
  Ch. 5 Lie-algebra Alt on a triangle.
* :func:`averaged` -- ``d∇α = 𝔡∇(Alt α)`` (Def. 5.2).
* :func:`wedge_curvature_solder_tet` -- the explicit end-of-Ch. 5 tetrahedron formula (discrete
  ``Ω∧θ``), equal to ``𝔡∇ Alt 𝔡∇ Alt θ̃`` to round-off.
* :func:`primal_dual_face`, :func:`primal_dual_tet`, :func:`primal_dual_dd`,
  :func:`primal_dual_wedge` -- Defs. 4.1-4.2 on the generalized dual complex.
* Mesh wrappers over a :class:`torchconn.mesh.TetMesh` (all tets at once):
  :func:`tet_transports`, :func:`tet_solder_sqrt`, :func:`averaged_dd_solder`,
  :func:`behs21_dd_solder`, :func:`wedge_solder`, :func:`curvature_2form`,
  :func:`primal_dual_dd_mesh`, :func:`primal_dual_wedge_mesh`.
"""
from __future__ import annotations

import itertools
import math
from functools import lru_cache

import torch

from .transport import dense_simplex_transports, orient, pair_list

__all__ = [
    "all_tuples",
    "distinct_tuples",
    "faces_of",
    "permutations_of",
    "ListForm",
    "unsymmetrized_vector",
    "unsymmetrized_lie",
    "alt_vector",
    "alt_lie",
    "averaged",
    "behs21",
    "connection_form",
    "solder_form",
    "solder_form_sqrt",
    "wedge_curvature_solder_tet",
    "averaged_dd_tet",
    "behs21_dd_tet",
    "primal_dual_face",
    "primal_dual_tet",
    "primal_dual_dd",
    "primal_dual_wedge",
    "tet_transports",
    "tet_solder_sqrt",
    "averaged_dd_solder",
    "behs21_dd_solder",
    "wedge_solder",
    "curvature_2form",
    "primal_dual_dd_mesh",
    "primal_dual_wedge_mesh",
    "TET_FACES",
    "TET_FACE_SIGNS",
    "FACE_EDGE_SIGNS",
]

# ----------------------------------------------------------------------------- templates

#: Local faces of a tet: face ``k`` is opposite local vertex ``k``, vertices ascending.
TET_FACES = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
#: Incidence of face ``k`` in ``∂[0123] = [123] - [023] + [013] - [012]``.
TET_FACE_SIGNS = (1, -1, 1, -1)
#: Incidence of the edge opposite slot ``m`` of ``[p<q<r]`` in ``∂[pqr] = [qr] - [pr] + [pq]``.
FACE_EDGE_SIGNS = (1, -1, 1)


@lru_cache(maxsize=None)
def _tuples_cpu(s: int, m: int) -> torch.Tensor:
    return torch.tensor(list(itertools.product(range(s), repeat=m)), dtype=torch.long).reshape(-1, m)


def all_tuples(s: int, m: int, device=None) -> torch.Tensor:
    """All ``s^m`` ordered ``m``-tuples of labels ``0..s-1`` as a ``(s^m, m)`` long tensor.

    Lexicographic order, so a dense form ``(..., s, .., s, value)`` reshaped to
    ``(..., s^m, value)`` lists its entries in this order.
    """
    return _tuples_cpu(s, m).to(device)


@lru_cache(maxsize=None)
def _perms(m: int) -> tuple[tuple[tuple[int, ...], int], ...]:
    """Permutations of ``range(m)`` with their signs."""
    out = []
    for p in itertools.permutations(range(m)):
        inv = sum(1 for a in range(m) for b in range(a + 1, m) if p[a] > p[b])
        out.append((p, -1 if inv % 2 else 1))
    return tuple(out)


def _check_T(T: torch.Tensor, fn: str) -> tuple[int, int, int]:
    if not torch.is_tensor(T) or T.ndim < 4 or T.shape[-4] != T.shape[-3] or T.shape[-1] != T.shape[-2]:
        raise ValueError(f"{fn}: transports T must have shape (..., s, s, n, n), got "
                         f"{tuple(T.shape) if torch.is_tensor(T) else type(T).__name__}")
    if not T.is_floating_point():
        raise TypeError(f"{fn}: transports T must be floating point, got {T.dtype}")
    return T.ndim - 4, T.shape[-4], T.shape[-1]


class ListForm:
    """A discrete form given only on a list of ordered label tuples.

    Args:
        values: ``(..., M, value...)`` (same batch dims as the transports ``T``).
        tuples: ``(M, k+1)`` long labels; row ``r`` is the tuple whose value is ``values[..., r]``.

    The operators of this module accept a ``ListForm`` wherever they accept a dense form; they
    raise if they need an entry the list lacks. Evaluating an operator with ``tuples=`` and
    wrapping the result in a ``ListForm`` chains operators without building dense tensors
    (this is how :func:`averaged_dd_tet` touches only the 24 + 12 distinct-label tuples).
    """

    def __init__(self, values: torch.Tensor, tuples) -> None:
        tuples = torch.as_tensor(tuples, dtype=torch.long)
        if tuples.ndim != 2 or tuples.shape[1] < 1:
            raise ValueError(f"ListForm: tuples must have shape (M, k+1), got {tuple(tuples.shape)}")
        if not torch.is_tensor(values) or values.ndim < 2:
            raise ValueError("ListForm: values must be a tensor (..., M, value...)")
        self.values = values
        self.tuples = tuples.cpu()

    def __repr__(self) -> str:
        return f"ListForm(values={tuple(self.values.shape)}, tuples={tuple(self.tuples.shape)})"


class _Src:
    """Uniform read access ``get(cols) -> (..., M, value...)`` to a dense form or a ListForm."""

    def __init__(self, form, batch_nd: int, L: int, s: int, value_nd: int, fn: str):
        self.batch_nd, self.L, self.s, self.fn = batch_nd, L, s, fn
        if isinstance(form, ListForm):
            tup = form.tuples
            if tup.numel() and (tup.min() < 0 or tup.max() >= s):
                raise ValueError(f"{fn}: ListForm labels must lie in [0, {s})")
            M = tup.shape[0]
            if form.values.shape[batch_nd] != M:
                raise ValueError(f"{fn}: ListForm values {tuple(form.values.shape)} do not list {M} tuples "
                                 f"at dim {batch_nd}")
            self.lookup = torch.full((s ** L,), -1, dtype=torch.long)
            self.lookup[_flat([tup[:, r] for r in range(L)], s)] = torch.arange(M)
            self.values = form.values
        else:
            shape = form.shape
            self.lookup = None
            self.values = form.reshape(*shape[:batch_nd], s ** L, *shape[batch_nd + L:])

    def get(self, cols) -> torch.Tensor:
        flat = _flat(cols, self.s)
        if self.lookup is not None:
            flat = self.lookup[flat]
            if (flat < 0).any():
                missing = [tuple(int(c[i]) for c in cols) for i in torch.nonzero(flat < 0).flatten()[:5]]
                raise ValueError(f"{self.fn}: the ListForm lacks the entries {missing} needed here")
        # index_select on one flattened label dim: much faster than multi-dim advanced indexing
        return self.values.index_select(self.batch_nd, flat.to(self.values.device))


def _flat(cols, s: int) -> torch.Tensor:
    idx = torch.zeros_like(cols[0])
    for c in cols:
        idx = idx * s + c
    return idx


def _labels(T: torch.Tensor, form, value_nd: int, fn: str, what: str) -> tuple[int, int]:
    """Return ``(batch_nd, L)``: number of batch dims and of label dims (``k+1``) of ``form``."""
    batch_nd, s, n = _check_T(T, fn)
    if isinstance(form, ListForm):
        vals, L = form.values, form.tuples.shape[1]
        if vals.ndim != batch_nd + 1 + value_nd:
            raise ValueError(f"{fn}: ListForm values of {what} must have shape (..., M, "
                             f"{'n, n' if value_nd == 2 else 'n'}) with {batch_nd} batch dims, got {tuple(vals.shape)}")
        vshape = vals.shape[batch_nd + 1:]
    else:
        if not torch.is_tensor(form):
            raise TypeError(f"{fn}: {what} must be a tensor or ListForm, got {type(form).__name__}")
        vals = form
        L = form.ndim - batch_nd - value_nd
        if L < 1:
            raise ValueError(f"{fn}: {what} of shape {tuple(form.shape)} has no label dims for T of shape "
                             f"{tuple(T.shape)} (expected (..., s, .., s, {'n, n' if value_nd == 2 else 'n'}) "
                             f"with the same number of batch dims as T)")
        labels = form.shape[batch_nd:batch_nd + L]
        if any(d != s for d in labels):
            raise ValueError(f"{fn}: label dims of {what} {tuple(labels)} must all equal s={s} "
                             f"(form shape {tuple(form.shape)}, T shape {tuple(T.shape)})")
        vshape = form.shape[batch_nd + L:]
    if vshape[0] != n:
        raise ValueError(f"{fn}: values of {what} must have leading size n={n}, got value shape {tuple(vshape)}")
    if value_nd == 2 and what.startswith("Lie") and vshape[1] != n:
        raise ValueError(f"{fn}: Lie-algebra values must be (n, n) = ({n}, {n}), got {tuple(vshape)}")
    if vals.dtype != T.dtype:
        raise TypeError(f"{fn}: {what} dtype {vals.dtype} differs from transports dtype {T.dtype}")
    return batch_nd, L


def _resolve_tuples(tuples, s: int, m: int, device, fn: str) -> tuple[torch.Tensor, bool]:
    if tuples is None:
        return all_tuples(s, m), True
    tuples = torch.as_tensor(tuples, dtype=torch.long).cpu()
    if tuples.ndim != 2 or tuples.shape[1] != m:
        raise ValueError(f"{fn}: tuples must have shape (M, {m}), got {tuple(tuples.shape)}")
    if tuples.numel() and (tuples.min() < 0 or tuples.max() >= s):
        raise ValueError(f"{fn}: tuple labels must lie in [0, {s}), got range "
                         f"[{int(tuples.min())}, {int(tuples.max())}]")
    return tuples, False


def _gather_T(T: torch.Tensor, batch_nd: int, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """``T[..., i, j, :, :]`` -> ``(..., M, n, n)``."""
    s = T.shape[-3]
    flatT = T.reshape(*T.shape[:batch_nd], s * s, *T.shape[-2:])
    return flatT.index_select(batch_nd, (i * s + j).to(T.device))


def _finish(out: torch.Tensor, dense: bool, batch_nd: int, s: int, m: int) -> torch.Tensor:
    if not dense:
        return out
    shape = out.shape
    return out.reshape(*shape[:batch_nd], *([s] * m), *shape[batch_nd + 1:])


def faces_of(tuples) -> torch.Tensor:
    """Distinct ``(k+1)``-tuples obtained by dropping one label of each row of ``tuples (M, k+2)``.

    The entries the unsymmetrized operators read (sorted unique rows, CPU long).
    """
    tuples = torch.as_tensor(tuples, dtype=torch.long).cpu()
    m = tuples.shape[1]
    sub = torch.cat([torch.cat([tuples[:, :j], tuples[:, j + 1:]], 1) for j in range(m)], 0)
    return torch.unique(sub, dim=0)


def permutations_of(tuples) -> torch.Tensor:
    """Distinct reorderings of each row of ``tuples (M, m)`` (the entries Alt reads)."""
    tuples = torch.as_tensor(tuples, dtype=torch.long).cpu()
    m = tuples.shape[1]
    sub = torch.cat([tuples[:, list(p)] for p, _ in _perms(m)], 0)
    return torch.unique(sub, dim=0)


def distinct_tuples(s: int, m: int) -> torch.Tensor:
    """All ordered ``m``-tuples of pairwise distinct labels in ``0..s-1`` (``(s!/(s-m)!, m)``)."""
    return torch.tensor(list(itertools.permutations(range(s), m)), dtype=torch.long).reshape(-1, m)


# ----------------------------------------------------------------------------- Def. 5.1

def unsymmetrized_vector(T: torch.Tensor, alpha, tuples=None, *,
                         matrix_values: bool = False) -> torch.Tensor:
    """Unsymmetrized covariant exterior derivative of a vector-valued k-form (Def. 5.1, corrected).

    ``⟨𝔡∇α, [x0..x(k+1)]⟩_{x0} = R_{x0x1} α[x1..x(k+1)] + Σ_{j=1}^{k+1} (-1)^j α[x0..x̂_j..x(k+1)]``
    (CONVENTIONS §1), every term in the fiber of ``x0``. Identical to the BEHS21 formula of Ch. 4.

    Args:
        T: ``(..., s, s, n, n)`` transports, ``T[i, j] = R_{x_i x_j}``.
        alpha: ``(..., s^(k+1) label dims, n)`` dense k-form (value in the fiber of the first
            label) or a :class:`ListForm`; with ``matrix_values=True`` values ``(n, m)`` acted on
            column-wise.
        tuples: ``None`` (all ordered ``(k+2)``-tuples, dense output) or ``(M, k+2)`` labels.

    Returns:
        ``(..., s, .., s [k+2 dims], n[, m])`` dense, or ``(..., M, n[, m])`` for given tuples.

    Example: with ``w = connection_form(T)`` (``matrix_values=True``) the output at ``(a,b,c)``
    is ``R_ab R_bc - R_ac = ⟨Ω,[abc]⟩_a^c``.
    """
    fn = "unsymmetrized_vector"
    value_nd = 2 if matrix_values else 1
    batch_nd, L = _labels(T, alpha, value_nd, fn, "alpha")
    s = T.shape[-3]
    tup, dense = _resolve_tuples(tuples, s, L + 1, T.device, fn)
    src = _Src(alpha, batch_nd, L, s, value_nd, fn)
    get = (lambda c: src.get(c)) if matrix_values else (lambda c: src.get(c).unsqueeze(-1))
    cols = [tup[:, r] for r in range(L + 1)]
    out = _gather_T(T, batch_nd, cols[0], cols[1]) @ get(cols[1:])
    for j in range(1, L + 1):
        term = get(cols[:j] + cols[j + 1:])
        out = out - term if j % 2 else out + term
    if not matrix_values:
        out = out.squeeze(-1)
    return _finish(out, dense, batch_nd, s, L + 1)


def unsymmetrized_lie(T: torch.Tensor, beta, tuples=None) -> torch.Tensor:
    """Unsymmetrized covariant exterior derivative of a Lie-algebra valued k-form (Def. 5.1, erratum 2).

    Evaluation ``x0``, cut ``x(k+1)``:
    ``R_{x0x1} β[x1..x(k+1)]_{x1}^{x(k+1)} + Σ_{j=1}^{k} (-1)^j β[s \\ x_j]_{x0}^{x(k+1)}
    + (-1)^{k+1} β[x0..xk]_{x0}^{xk} R_{xk x(k+1)}``.

    Args:
        T: ``(..., s, s, n, n)`` transports.
        beta: ``(..., s^(k+1) label dims, n, n)`` (evaluation = first label, cut = last label)
            or a :class:`ListForm`.
        tuples: ``None`` (dense over all ``(k+2)``-tuples) or ``(M, k+2)`` labels.

    Returns:
        ``(..., s, .., s [k+2], n, n)`` or ``(..., M, n, n)``; evaluation first, cut last label.

    Invariant: with ``Ω = unsymmetrized_vector(T, connection_form(T), matrix_values=True)`` the
    output vanishes identically on every tuple (differential Bianchi, Ch. 5).
    """
    fn = "unsymmetrized_lie"
    batch_nd, L = _labels(T, beta, 2, fn, "Lie form beta")
    s = T.shape[-3]
    k = L - 1
    tup, dense = _resolve_tuples(tuples, s, L + 1, T.device, fn)
    src = _Src(beta, batch_nd, L, s, 2, fn)
    cols = [tup[:, r] for r in range(L + 1)]
    out = _gather_T(T, batch_nd, cols[0], cols[1]) @ src.get(cols[1:])
    for j in range(1, k + 1):
        term = src.get(cols[:j] + cols[j + 1:])
        out = out - term if j % 2 else out + term
    last = src.get(cols[:L]) @ _gather_T(T, batch_nd, cols[k], cols[k + 1])
    out = out - last if (k + 1) % 2 else out + last
    return _finish(out, dense, batch_nd, s, L + 1)


# ----------------------------------------------------------------------------- Def. 5.2

def alt_vector(T: torch.Tensor, alpha, tuples=None, *, matrix_values: bool = False) -> torch.Tensor:
    """Alternation of a vector-valued k-form (Def. 5.2 with ``1/(k+1)!``, erratum 8).

    ``Alt(α)[x0..xk] = 1/(k+1)! Σ_{σ ∈ S_{k+1}} sgn(σ) R_{x0 xσ(0)} α[xσ(0)..xσ(k)]``, in the
    fiber of ``x0``.

    Invariants (tested): exactly antisymmetric under permutations fixing the first label;
    for ``k = 1``, ``Alt(α)[x1x0] = -R_{x1x0} Alt(α)[x0x1]``; ``Alt(θ̃) = θ̃`` when
    ``θ̃_ji = -R_ji θ̃_ij``.

    Args:
        T: ``(..., s, s, n, n)``; alpha: ``(..., s^(k+1), n[, m])`` dense or a :class:`ListForm`.
        tuples: ``None`` (dense over all ``(k+1)``-tuples) or ``(M, k+1)`` labels.

    Returns:
        Same layout as a dense ``alpha`` or ``(..., M, n[, m])``.
    """
    fn = "alt_vector"
    value_nd = 2 if matrix_values else 1
    batch_nd, L = _labels(T, alpha, value_nd, fn, "alpha")
    s = T.shape[-3]
    tup, dense = _resolve_tuples(tuples, s, L, T.device, fn)
    src = _Src(alpha, batch_nd, L, s, value_nd, fn)
    get = (lambda c: src.get(c)) if matrix_values else (lambda c: src.get(c).unsqueeze(-1))
    cols = [tup[:, r] for r in range(L)]
    out = None
    # group permutations by sigma(0): one transport R_{x0 x_sigma(0)} per group
    for first in range(L):
        acc = None
        for p, sgn in _perms(L):
            if p[0] != first:
                continue
            term = get([cols[p[r]] for r in range(L)])
            acc = sgn * term if acc is None else acc + sgn * term
        if first > 0:
            acc = _gather_T(T, batch_nd, cols[0], cols[first]) @ acc
        out = acc if out is None else out + acc
    out = out / math.factorial(L)
    if not matrix_values:
        out = out.squeeze(-1)
    return _finish(out, dense, batch_nd, s, L)


def alt_lie(T: torch.Tensor, beta, tuples=None) -> torch.Tensor:
    """Alternation of a Lie-algebra valued k-form, ``k <= 2`` (Ch. 5; CONVENTIONS §1).

    * ``k = 0``: the identity.
    * ``k = 1``: ``Alt(β)[x0x1] = ½(β[x0x1]_{x0}^{x1} - R_{x0x1} β[x1x0]_{x1}^{x0} R_{x0x1})``
      (the reversed edge carried to evaluation ``x0``, cut ``x1``); it fixes every
      ``𝔡∇φ`` of a Lie 0-form φ.
    * ``k = 2`` on ``[x0x1x2]``: for each vertex ``y`` with positively ordered ``[y y' y'']``
      (the cyclic rotations of ``(x0,x1,x2)``) take ``A_y = ½(β[y y' y'']_y^{y''} -
      β[y y'' y']_y^{y'} R_{y'y''})``, carry it to evaluation ``x0`` / cut ``x2`` by
      ``R_{x0 y} A_y R_{y'' x2}`` and average the three. ``Alt(Ω) = Ω`` for ``Ω = 𝔡∇w``.

    Args:
        T: ``(..., s, s, n, n)``; beta: ``(..., s^(k+1), n, n)`` (evaluation first, cut last)
            or a :class:`ListForm`.
        tuples: ``None`` (dense) or ``(M, k+1)`` labels.

    Returns:
        Same layout as a dense ``beta`` or ``(..., M, n, n)``.
    """
    fn = "alt_lie"
    batch_nd, L = _labels(T, beta, 2, fn, "Lie form beta")
    s = T.shape[-3]
    if L > 3:
        raise ValueError(f"alt_lie: the Lie-algebra alternation is defined for k <= 2 (report Ch. 5), got k={L - 1}")
    tup, dense = _resolve_tuples(tuples, s, L, T.device, fn)
    src = _Src(beta, batch_nd, L, s, 2, fn)
    cols = [tup[:, r] for r in range(L)]
    if L == 1:
        out = src.get(cols)
    elif L == 2:
        x0, x1 = cols
        R01 = _gather_T(T, batch_nd, x0, x1)
        out = 0.5 * (src.get([x0, x1]) - R01 @ src.get([x1, x0]) @ R01)
    else:
        x0, x2 = cols[0], cols[2]
        out = None
        for r in range(3):
            y, y1, y2 = cols[r], cols[(r + 1) % 3], cols[(r + 2) % 3]
            A = src.get([y, y1, y2]) - src.get([y, y2, y1]) @ _gather_T(T, batch_nd, y1, y2)
            A = _gather_T(T, batch_nd, x0, y) @ A @ _gather_T(T, batch_nd, y2, x2)
            out = A if out is None else out + A
        out = out / 6.0
    return _finish(out, dense, batch_nd, s, L)


def averaged(T: torch.Tensor, alpha, tuples=None, *, lie: bool = False,
             matrix_values: bool = False) -> torch.Tensor:
    """Averaged (anti-symmetrized) covariant exterior derivative ``d∇α = 𝔡∇(Alt α)`` (Def. 5.2).

    Vector-valued by default (``alt_vector`` then ``unsymmetrized_vector``, value in the fiber of
    the first label); ``lie=True`` uses ``alt_lie`` then ``unsymmetrized_lie`` (evaluation first,
    cut last label; ``k <= 2``). Shapes as in :func:`unsymmetrized_vector`. With ``tuples`` the
    alternation is evaluated only on the faces those tuples read (:func:`faces_of`).

    Invariants (tested): ``d∇Ω = 0`` for ``Ω = 𝔡∇w`` (``lie=True``); swapping the last two
    vertices flips the sign exactly (Alt is antisymmetric with the first label fixed and the
    transported term keeps ``R_{x0x1}``); other odd relabelings move the transport paths and
    flip the sign only up to curvature terms; gauge covariant (``G_{x0}`` on vector values).
    """
    value_nd = 2 if (lie or matrix_values) else 1
    _, L = _labels(T, alpha, value_nd, "averaged", "Lie form beta" if lie else "alpha")
    if tuples is not None:
        tuples, _ = _resolve_tuples(tuples, T.shape[-3], L + 1, T.device, "averaged")
        need = faces_of(tuples)
    if lie:
        alt = alt_lie(T, alpha) if tuples is None else ListForm(alt_lie(T, alpha, need), need)
        return unsymmetrized_lie(T, alt, tuples)
    alt = (alt_vector(T, alpha, matrix_values=matrix_values) if tuples is None
           else ListForm(alt_vector(T, alpha, need, matrix_values=matrix_values), need))
    return unsymmetrized_vector(T, alt, tuples, matrix_values=matrix_values)


def behs21(T: torch.Tensor, alpha: torch.Tensor, tuples=None, *, matrix_values: bool = False) -> torch.Tensor:
    """The BEHS21 / Sch18 covariant exterior derivative quoted at the start of Ch. 4.

    ``⟨d∇α,[x0..x(k+1)]⟩_{x0} = R_{x0x1} α[x1..x(k+1)]_{x1} + Σ_i (-1)^i α[x0..x̂_i..x(k+1)]_{x0}``.
    This is literally the corrected vector version of Def. 5.1 (:func:`unsymmetrized_vector`)
    applied to the *plain*, non-alternated form (e.g. θ_ij = v_j - v_i); Def. 5.2 differs only by
    alternating the argument first. Applied twice to θ on ``[abcd]`` it gives
    ``(R_ab R_bc - R_ac) θ_cd`` (Ch. 4, erratum 1), which does not converge to Ω∧θ.
    """
    return unsymmetrized_vector(T, alpha, tuples, matrix_values=matrix_values)


# ----------------------------------------------------------------------------- forms

def connection_form(T: torch.Tensor) -> torch.Tensor:
    """Connection 1-form ``w[i, j] = R_ij - I`` (eq. 3.1.2) as a dense ``(..., s, s, n, n)`` form.

    Use it as a vector-valued 1-form with matrix values acted on column-wise
    (``unsymmetrized_vector(T, w, matrix_values=True)`` gives ``⟨Ω,[abc]⟩_a^c = R_ab R_bc - R_ac``,
    Ch. 5), or as a Lie-valued 1-form with evaluation ``i`` and cut ``j`` (Remark 2.2).
    ``R_ij w_ji = -w_ij``.
    """
    _check_T(T, "connection_form")
    n = T.shape[-1]
    return T - torch.eye(n, dtype=T.dtype, device=T.device)


def solder_form(points: torch.Tensor) -> torch.Tensor:
    """Discrete solder form ``θ[i, j] = v_j - v_i`` on a simplex (Sec. 3.3, global coordinate frame).

    Args:
        points: ``(..., s, d)`` vertex positions.

    Returns:
        ``(..., s, s, d)``, value "in the fiber of the first label" expressed in the global frame
        (the report's numerical setting, where every fiber uses the coordinate frame).
    """
    if not torch.is_tensor(points) or points.ndim < 2:
        raise ValueError(f"solder_form: points must have shape (..., s, d), got "
                         f"{tuple(points.shape) if torch.is_tensor(points) else type(points).__name__}")
    return points.unsqueeze(-3) - points.unsqueeze(-2)  # [i, j] = p_j - p_i


def solder_form_sqrt(T_half: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Half-transported solder form ``θ̃[i, j] = √R_ij θ_ij = √R_ij (v_j - v_i)`` (Sec. 3.3).

    The solder form is taken at the edge midpoint in the global coordinate frame and carried to
    ``x_i`` by the half transport (report Fig. 3.2).

    Args:
        T_half: ``(..., s, s, n, n)`` half transports ``√R_{x_i x_j}`` (midpoint of ``ij`` ->
            ``x_i``; ``so3.sqrt`` of ``R_ij`` for a discrete connection, ``exp(½ ω_m[v_j - v_i])``
            in the experiments); ``√R_ji = √R_ij^T``.
        points: ``(..., s, n)`` vertex positions, or an already formed dense solder form
            ``θ (..., s, s, n)`` (:func:`solder_form`); the two are told apart by their number of
            dims relative to ``T_half`` (same number of batch dims).

    Returns:
        ``(..., s, s, n)`` in the fiber of the first label; ``R_ji θ̃_ij = -θ̃_ji`` whenever
        ``R_ij = √R_ij²`` (erratum 9).
    """
    batch_nd, s_, n = _check_T(T_half, "solder_form_sqrt")
    if not torch.is_tensor(points):
        raise TypeError(f"solder_form_sqrt: points must be a tensor, got {type(points).__name__}")
    if points.ndim == batch_nd + 2 and points.shape[-2:] == (s_, n):
        theta = solder_form(points)
    elif points.ndim == batch_nd + 3 and points.shape[-3:] == (s_, s_, n):
        theta = points
    else:
        raise ValueError(f"solder_form_sqrt: expected points (..., {s_}, {n}) or a solder form "
                         f"(..., {s_}, {s_}, {n}) with {batch_nd} batch dims like T_half "
                         f"{tuple(T_half.shape)}, got {tuple(points.shape)}")
    return (T_half @ theta.unsqueeze(-1)).squeeze(-1)


# ----------------------------------------------------------------------------- tet formulas

_TET = torch.tensor([[0, 1, 2, 3]], dtype=torch.long)


def _check_tet(T: torch.Tensor, theta: torch.Tensor, fn: str) -> None:
    batch_nd, s, n = _check_T(T, fn)
    if s != 4:
        raise ValueError(f"{fn}: expects tet transports (..., 4, 4, n, n), got {tuple(T.shape)}")
    if theta.shape[-3:] != (4, 4, n):
        raise ValueError(f"{fn}: expects a dense 1-form (..., 4, 4, {n}), got {tuple(theta.shape)}")


def wedge_curvature_solder_tet(T: torch.Tensor, theta_tilde: torch.Tensor) -> torch.Tensor:
    """Explicit discrete ``Ω∧θ`` on a tet ``[abcd]`` at vertex ``a`` (end of report Ch. 5).

    With ``R_xy = T[x, y]`` and ``θ̃_xy = theta_tilde[x, y]`` (labels ``a,b,c,d = 0,1,2,3``)::

        1/6 ( (R_ac R_cb - R_ad R_db) θ̃_ba - (R_ab R_bc - R_ad R_dc) θ̃_ca + (R_ac - R_ab R_bd R_dc) θ̃_cb
            + (R_ab R_bd - R_ac R_cd) θ̃_da - (R_ad - R_ab R_bc R_cd) θ̃_db + (R_ad - R_ab R_bd) θ̃_dc )
      + 1/3 ( (R_ac - R_ab R_bc) θ̃_cb - (R_ad - R_ab R_bd) θ̃_db + (R_ad - R_ab R_bd) θ̃_dc )
      + 1/2 (R_ab R_bc - R_ac) θ̃_cd

    Every bracket is a curvature evaluation; equals ``𝔡∇ Alt 𝔡∇ Alt θ̃`` at ``[abcd]`` to
    round-off whenever ``θ̃_ji = -R_ji θ̃_ij``.

    Args:
        T: ``(..., 4, 4, n, n)``; theta_tilde: ``(..., 4, 4, n)``.

    Returns:
        ``(..., n)`` in the fiber of ``a``.
    """
    _check_tet(T, theta_tilde, "wedge_curvature_solder_tet")
    R = lambda i, j: T[..., i, j, :, :]  # noqa: E731
    th = lambda i, j: theta_tilde[..., i, j, :].unsqueeze(-1)  # noqa: E731
    a, b, c, d = 0, 1, 2, 3
    Rab, Rac, Rad, Rbc, Rbd, Rcd = R(a, b), R(a, c), R(a, d), R(b, c), R(b, d), R(c, d)
    Rcb, Rdb, Rdc = R(c, b), R(d, b), R(d, c)
    RabRbd = Rab @ Rbd
    RabRbc = Rab @ Rbc
    sixth = ((Rac @ Rcb - Rad @ Rdb) @ th(b, a)
             - (RabRbc - Rad @ Rdc) @ th(c, a)
             + (Rac - RabRbd @ Rdc) @ th(c, b)
             + (RabRbd - Rac @ Rcd) @ th(d, a)
             - (Rad - RabRbc @ Rcd) @ th(d, b)
             + (Rad - RabRbd) @ th(d, c))
    third = ((Rac - RabRbc) @ th(c, b)
             - (Rad - RabRbd) @ th(d, b)
             + (Rad - RabRbd) @ th(d, c))
    half = (RabRbc - Rac) @ th(c, d)
    return (sixth / 6.0 + third / 3.0 + half / 2.0).squeeze(-1)


def averaged_dd_tet(T: torch.Tensor, theta_tilde: torch.Tensor) -> torch.Tensor:
    """``⟨d∇d∇θ, [abcd]⟩_a = 𝔡∇ Alt 𝔡∇ Alt θ̃`` at ``[0123]`` (Def. 5.2 twice, CONVENTIONS §1).

    Computed through the generic operators. ``T (..., 4, 4, n, n)``, ``theta_tilde (..., 4, 4, n)``
    -> ``(..., n)`` in the fiber of local vertex 0. Equals :func:`wedge_curvature_solder_tet` to
    round-off. The first Alt is a no-op on ``θ̃`` (``Alt(θ̃)_ij = ½(θ̃_ij - R_ij θ̃_ji) = θ̃_ij``
    since ``θ̃_ji = -R_ji θ̃_ij``); it matters for forms without that symmetry (plain θ).
    """
    _check_tet(T, theta_tilde, "averaged_dd_tet")
    # only distinct-label entries are ever read: 12 pairs -> 24 triples -> 4 faces -> [0123]
    triples = distinct_tuples(4, 3)
    two = ListForm(averaged(T, theta_tilde, triples), triples)
    return averaged(T, two, _TET).squeeze(-2)


def behs21_dd_tet(T: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """BEHS21 twice on the plain solder form at ``[0123]``: ``(R_ab R_bc - R_ac) θ_cd`` (Ch. 4).

    ``T (..., 4, 4, n, n)``, ``theta (..., 4, 4, n)`` -> ``(..., n)`` in the fiber of vertex 0.
    """
    _check_tet(T, theta, "behs21_dd_tet")
    faces = faces_of(_TET)
    return behs21(T, ListForm(behs21(T, theta, faces), faces), _TET).squeeze(-2)


# ----------------------------------------------------------------------------- primal-dual

def _check_pd(rot: torch.Tensor, values: torch.Tensor, m: int, fn: str, what: str) -> None:
    if rot.ndim < 3 or rot.shape[-3] != m or rot.shape[-1] != rot.shape[-2]:
        raise ValueError(f"{fn}: {what} transports must have shape (..., {m}, n, n), got {tuple(rot.shape)}")
    if values.shape[-2:] != (m, rot.shape[-1]):
        raise ValueError(f"{fn}: {what} values must have shape (..., {m}, {rot.shape[-1]}), got {tuple(values.shape)}")


def _signs_like(signs, default, like: torch.Tensor, m: int, fn: str) -> torch.Tensor:
    if signs is None:
        return torch.tensor(default, dtype=like.dtype, device=like.device)
    signs = torch.as_tensor(signs, device=like.device).to(like.dtype)
    if signs.shape[-1:] != (m,):
        raise ValueError(f"{fn}: signs must have shape (..., {m}), got {tuple(signs.shape)}")
    return signs


def primal_dual_face(face_edge_rot: torch.Tensor, edge_values: torch.Tensor, signs=None) -> torch.Tensor:
    """Primal-dual d∇ of an edge-centred 1-form on a triangle (Def. 4.2; eq. 3.3.1 for θ).

    ``⟨d∇α, f⟩_{c_f} = Σ_e sign_e R_{c_f c_e} ⟨α, e⟩_{c_e}``.

    Args:
        face_edge_rot: ``(..., 3, n, n)``, ``R_{c_f c_e}`` (edge barycentre -> face barycentre).
        edge_values: ``(..., 3, n)`` values at ``c_e`` for the edges in their stored orientation.
        signs: ``(..., 3)`` incidence coefficients; default ``(+1, -1, +1)``
            (edges ``bc, ac, ab`` of ``[a<b<c]``, as ``TetMesh.face_edges``).

    Returns:
        ``(..., n)`` at the face barycentre.
    """
    fn = "primal_dual_face"
    _check_pd(face_edge_rot, edge_values, 3, fn, "face-edge")
    sg = _signs_like(signs, FACE_EDGE_SIGNS, edge_values, 3, fn)
    return ((face_edge_rot @ edge_values.unsqueeze(-1)).squeeze(-1) * sg.unsqueeze(-1)).sum(-2)


def primal_dual_tet(tet_face_rot: torch.Tensor, face_values: torch.Tensor, signs=None) -> torch.Tensor:
    """Primal-dual d∇ of a face-centred 2-form on a tet (Def. 4.2).

    ``⟨d∇α, t⟩_{c_t} = Σ_f sign_f R_{c_t c_f} ⟨α, f⟩_{c_f}``.

    Args:
        tet_face_rot: ``(..., 4, n, n)``, ``R_{c_t c_f}``; face ``k`` opposite local vertex ``k``.
        face_values: ``(..., 4, n)`` at ``c_f``.
        signs: ``(..., 4)``; default ``(+1, -1, +1, -1)`` from ``∂[abcd] = [bcd]-[acd]+[abd]-[abc]``.

    Returns:
        ``(..., n)`` at the tet barycentre.
    """
    fn = "primal_dual_tet"
    _check_pd(tet_face_rot, face_values, 4, fn, "tet-face")
    sg = _signs_like(signs, TET_FACE_SIGNS, face_values, 4, fn)
    return ((tet_face_rot @ face_values.unsqueeze(-1)).squeeze(-1) * sg.unsqueeze(-1)).sum(-2)


@lru_cache(maxsize=None)
def _tet_face_edge_table() -> tuple[tuple[tuple[int, ...], ...], tuple[tuple[int, ...], ...]]:
    """Local tet template: ``edge[k][m]`` = pair_list(4) index of the edge opposite slot ``m`` of
    face ``k``; ``coef[k][m]`` = ``TET_FACE_SIGNS[k] * FACE_EDGE_SIGNS[m]`` (orientation i<j)."""
    index = {p: a for a, p in enumerate(pair_list(4))}
    edge, coef = [], []
    for k, (p, q, r) in enumerate(TET_FACES):
        opp = ((q, r), (p, r), (p, q))
        edge.append(tuple(index[e] for e in opp))
        coef.append(tuple(TET_FACE_SIGNS[k] * FACE_EDGE_SIGNS[m] for m in range(3)))
    return tuple(edge), tuple(coef)


@lru_cache(maxsize=None)
def _tet_edge_slots() -> tuple[tuple[int, ...], tuple[int, ...]]:
    """For each local edge (pair_list(4) order): flat slot ``3k+m`` with coefficient ``+1`` and ``-1``."""
    edge, coef = _tet_face_edge_table()
    plus, minus = [0] * 6, [0] * 6
    for k in range(4):
        for m in range(3):
            (plus if coef[k][m] > 0 else minus)[edge[k][m]] = 3 * k + m
    return tuple(plus), tuple(minus)


def _check_pd_tet(tet_face_rot, face_edge_rot, edge_values, fn):
    if tet_face_rot.ndim < 3 or tet_face_rot.shape[-3] != 4 or tet_face_rot.shape[-1] != tet_face_rot.shape[-2]:
        raise ValueError(f"{fn}: tet_face_rot must have shape (..., 4, n, n), got {tuple(tet_face_rot.shape)}")
    n = tet_face_rot.shape[-1]
    if face_edge_rot.shape[-4:] != (4, 3, n, n):
        raise ValueError(f"{fn}: face_edge_rot must have shape (..., 4, 3, {n}, {n}), got {tuple(face_edge_rot.shape)}")
    if edge_values.shape[-2:] != (6, n):
        raise ValueError(f"{fn}: edge_values must have shape (..., 6, {n}), got {tuple(edge_values.shape)}")


def primal_dual_dd(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor) -> torch.Tensor:
    """Primal-dual ``d∇d∇α`` on one tet template (Def. 4.2 twice, Ch. 4).

    ``Σ_f sign_f R_{c_t c_f} Σ_{e ⊂ f} sign_{fe} R_{c_f c_e} α_e``.

    Local template: face ``k`` = ``TET_FACES[k]`` (opposite vertex ``k``, ascending), slot ``m``
    of face ``[p<q<r]`` = the edge opposite its ``m``-th vertex (``qr, pr, pq``).

    Args:
        tet_face_rot: ``(..., 4, n, n)`` ``R_{c_t c_f}``.
        face_edge_rot: ``(..., 4, 3, n, n)`` ``R_{c_f c_e}`` for face ``k``, slot ``m``.
        edge_values: ``(..., 6, n)`` at ``c_e``, local edges in ``pair_list(4)`` order, oriented
            ``i -> j`` with ``i < j``.

    Returns:
        ``(..., n)`` at the tet barycentre.
    """
    fn = "primal_dual_dd"
    _check_pd_tet(tet_face_rot, face_edge_rot, edge_values, fn)
    edge, _ = _tet_face_edge_table()
    idx = torch.tensor(edge, dtype=torch.long, device=edge_values.device)  # (4, 3)
    vals = edge_values[..., idx, :]  # (..., 4, 3, n)
    faces = primal_dual_face(face_edge_rot, vals)  # default FACE_EDGE_SIGNS per slot
    return primal_dual_tet(tet_face_rot, faces)


def primal_dual_wedge(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor) -> torch.Tensor:
    """Curvature-pair form of the primal-dual ``d∇d∇α`` = discrete ``Ω∧α`` (Ch. 4).

    ``Σ_{(e,e')} ⟨Ω,[c_{f_e}, c_e, c_{f_e'}, c_t]⟩_{c_t}^{c_e} α_e`` with the two-prong
    ``R_{c_t c_{f_e}} R_{c_{f_e} c_e} - R_{c_t c_{f_e'}} R_{c_{f_e'} c_e}``: for each tet edge
    ``e = (i<j)``, ``f_e`` is the face in whose induced boundary it appears with coefficient
    ``+1`` and ``f_e'`` the one with ``-1``. Equals :func:`primal_dual_dd` for any transports.
    Same arguments and output as :func:`primal_dual_dd`.
    """
    fn = "primal_dual_wedge"
    _check_pd_tet(tet_face_rot, face_edge_rot, edge_values, fn)
    plus, minus = _tet_edge_slots()
    dev = edge_values.device
    plus = torch.tensor(plus, dtype=torch.long, device=dev)
    minus = torch.tensor(minus, dtype=torch.long, device=dev)
    path = tet_face_rot.unsqueeze(-3) @ face_edge_rot  # (..., 4, 3, n, n): R_{c_t c_f} R_{c_f c_e}
    path = path.flatten(-4, -3)  # (..., 12, n, n), slot 3k+m
    omega = path[..., plus, :, :] - path[..., minus, :, :]  # (..., 6, n, n) two-prongs
    return (omega @ edge_values.unsqueeze(-1)).squeeze(-1).sum(-2)


# ----------------------------------------------------------------------------- mesh wrappers

def _check_mesh_rot(edge_rot: torch.Tensor, mesh, fn: str) -> None:
    if not torch.is_tensor(edge_rot) or edge_rot.ndim != 3 or edge_rot.shape[-1] != edge_rot.shape[-2]:
        raise ValueError(f"{fn}: edge_rot must have shape (E, n, n), got "
                         f"{tuple(edge_rot.shape) if torch.is_tensor(edge_rot) else type(edge_rot).__name__}")
    E = mesh.edges.shape[0]
    if edge_rot.shape[0] != E:
        raise ValueError(f"{fn}: edge_rot has {edge_rot.shape[0]} rotations but the mesh has {E} edges")


def tet_transports(edge_rot: torch.Tensor, mesh) -> torch.Tensor:
    """Dense per-tet transports ``(T, 4, 4, n, n)``, ``[t, i, j] = R_{tets[t,i] tets[t,j]}``.

    Args:
        edge_rot: ``(E, n, n)`` rotations ``R_ij`` of the canonical edges ``mesh.edges``.
        mesh: a :class:`torchconn.mesh.TetMesh` (uses ``tet_edges``, ``tet_edge_signs``).
    """
    _check_mesh_rot(edge_rot, mesh, "tet_transports")
    pair = orient(edge_rot, mesh.tet_edges.to(edge_rot.device), mesh.tet_edge_signs.to(edge_rot.device))
    return dense_simplex_transports(pair, 4)


def _check_frames(frames, mesh, edge_rot, fn):
    V = mesh.vertices.shape[0]
    n = edge_rot.shape[-1]
    if frames.shape != (V, 3, 3) or n != 3:
        raise ValueError(f"{fn}: frames must be (V, 3, 3) = ({V}, 3, 3) rotations and n = 3, got frames "
                         f"{tuple(frames.shape)}, n = {n}")
    return frames.to(device=edge_rot.device, dtype=edge_rot.dtype)


def _tet_points(edge_rot, mesh):
    return mesh.vertices.to(device=edge_rot.device, dtype=edge_rot.dtype)[mesh.tets.to(edge_rot.device)]


def _tet_theta(edge_rot: torch.Tensor, mesh, frames, fn: str) -> torch.Tensor:
    """Plain per-tet ``θ[t, i, j] = F_i^T (v_j - v_i)`` ``(T, 4, 4, n)`` (fiber of ``tets[t,i]``)."""
    pts = _tet_points(edge_rot, mesh)
    theta = solder_form(pts)
    if frames is None:
        if edge_rot.shape[-1] != pts.shape[-1]:
            raise ValueError(f"{fn}: rank n={edge_rot.shape[-1]} differs from the ambient dimension "
                             f"{pts.shape[-1]}; the solder form needs n = 3")
        return theta
    F = _check_frames(frames, mesh, edge_rot, fn)[mesh.tets.to(edge_rot.device)]  # (T, 4, 3, 3)
    return (F.unsqueeze(-3).transpose(-1, -2) @ theta.unsqueeze(-1)).squeeze(-1)


def tet_solder_sqrt(edge_rot: torch.Tensor, mesh, frames=None, half_rot=None) -> torch.Tensor:
    """Per-tet dense ``θ̃[t, i, j] = √R_ij θ_ij`` ``(T, 4, 4, n)``, value in the fiber of ``tets[t,i]``.

    Without ``frames`` every fiber uses the global coordinate frame (report Sec. 3.3):
    ``θ_ij = v_j - v_i`` and ``√R_ij = half_rot`` (default ``so3.sqrt(edge_rot)``; pass
    ``half_rot (E, n, n)`` for ``n != 3`` or for the experiments' ``exp(½ ω_m[v_j - v_i])``).

    With ``frames (V, 3, 3)`` (column ``c`` of ``frames[v]`` = frame vector ``c`` of the fiber at
    ``v`` in ambient coordinates) ``edge_rot`` is read in those frames, ``R'_ij = F_i^T R_ij F_j``
    with ``R`` in ambient coordinates. The edge midpoint keeps the ambient frame as in the
    report, so ``θ̃'_ij = F_i^T √R_ij (v_j - v_i)`` with ``√R_ij = sqrt(F_i R'_ij F_j^T)``, or
    ``√R_ij = F_i half_rot_ij F_j^T`` when ``half_rot`` (in vertex frames) is given. This makes
    the result exactly gauge covariant (``G_i = F_i^T``) and keeps ``θ̃_ji = -R'_ji θ̃_ij``.
    """
    fn = "tet_solder_sqrt"
    _check_mesh_rot(edge_rot, mesh, fn)
    if half_rot is not None and half_rot.shape != edge_rot.shape:
        raise ValueError(f"{fn}: half_rot shape {tuple(half_rot.shape)} must equal edge_rot shape {tuple(edge_rot.shape)}")
    pts = _tet_points(edge_rot, mesh)
    if frames is None:
        if half_rot is None:
            if edge_rot.shape[-1] != 3:
                raise ValueError(f"{fn}: half transports √R are computed with so3.sqrt only for n = 3; "
                                 f"pass half_rot for n = {edge_rot.shape[-1]}")
            from . import so3
            half_rot = so3.sqrt(edge_rot)
        if edge_rot.shape[-1] != pts.shape[-1]:
            raise ValueError(f"{fn}: rank n={edge_rot.shape[-1]} differs from the ambient dimension "
                             f"{pts.shape[-1]}; the solder form needs n = 3")
        return solder_form_sqrt(tet_transports(half_rot, mesh), pts)
    from . import so3
    Fv = _check_frames(frames, mesh, edge_rot, fn)
    e = mesh.edges.to(edge_rot.device)
    Fi, Fj = Fv[e[:, 0]], Fv[e[:, 1]]
    if half_rot is None:
        half_amb = so3.sqrt(Fi @ edge_rot @ Fj.transpose(-1, -2))
    else:
        half_amb = Fi @ half_rot @ Fj.transpose(-1, -2)
    th_amb = solder_form_sqrt(tet_transports(half_amb, mesh), pts)
    F = Fv[mesh.tets.to(edge_rot.device)]  # (T, 4, 3, 3)
    return (F.unsqueeze(-3).transpose(-1, -2) @ th_amb.unsqueeze(-1)).squeeze(-1)


def averaged_dd_solder(edge_rot: torch.Tensor, mesh, frames=None, half_rot=None) -> torch.Tensor:
    """Averaged ``d∇d∇θ = 𝔡∇ Alt 𝔡∇ Alt θ̃`` on every tet: ``(T, n)`` in the fiber of ``tets[t,0]``.

    Report Def. 5.2 twice (CONVENTIONS §1); arguments as in :func:`tet_solder_sqrt`. Divide by
    the tet volume to compare with the smooth ``Ω∧θ``. For ``n = 3`` this is evaluated by the
    fused closed form :func:`torchconn.fast.tet_dd_solder` (the Ch. 5 tet formula, equal to
    the generic ``averaged_dd_tet`` on the dense tables to round-off); other ranks use the
    generic operators.
    """
    if _fast_ok(edge_rot, mesh, frames, half_rot, "averaged_dd_solder"):
        from .fast import tet_dd_solder
        return tet_dd_solder(edge_rot, mesh, half_rot=half_rot, frames=frames)
    T = tet_transports(edge_rot, mesh)
    return averaged_dd_tet(T, tet_solder_sqrt(edge_rot, mesh, frames, half_rot))


def _fast_ok(edge_rot, mesh, frames, half_rot, fn) -> bool:
    """Whether the fused n = 3 tet kernel applies (after the same argument checks as the generic path)."""
    _check_mesh_rot(edge_rot, mesh, fn)
    if edge_rot.shape[-1] != 3 or mesh.vertices.shape[-1] != 3:
        return False
    if half_rot is not None and half_rot.shape != edge_rot.shape:
        raise ValueError(f"{fn}: half_rot shape {tuple(half_rot.shape)} must equal edge_rot shape {tuple(edge_rot.shape)}")
    if frames is not None:
        _check_frames(frames, mesh, edge_rot, fn)
    return True


def behs21_dd_solder(edge_rot: torch.Tensor, mesh, frames=None) -> torch.Tensor:
    """BEHS21 twice on the plain solder form on every tet: ``(T, n)``, ``(R_ab R_bc - R_ac) θ_cd`` (Ch. 4)."""
    T = tet_transports(edge_rot, mesh)
    return behs21_dd_tet(T, _tet_theta(edge_rot, mesh, frames, "behs21_dd_solder"))


def wedge_solder(edge_rot: torch.Tensor, mesh, frames=None, half_rot=None) -> torch.Tensor:
    """Explicit Ch. 5 ``Ω∧θ`` (:func:`wedge_curvature_solder_tet`) on every tet: ``(T, n)`` at ``tets[t,0]``.

    For ``n = 3`` evaluated by the fused regrouping of the same formula
    (:func:`torchconn.fast.tet_dd_solder`); other ranks use the dense tables.
    """
    if _fast_ok(edge_rot, mesh, frames, half_rot, "wedge_solder"):
        from .fast import tet_dd_solder
        return tet_dd_solder(edge_rot, mesh, half_rot=half_rot, frames=frames)
    T = tet_transports(edge_rot, mesh)
    return wedge_curvature_solder_tet(T, tet_solder_sqrt(edge_rot, mesh, frames, half_rot))


def curvature_2form(edge_rot: torch.Tensor, mesh) -> torch.Tensor:
    """Curvature ``⟨Ω,[abc]⟩_a^c = R_ab R_bc - R_ac`` on every face ``[a<b<c]``: ``(F, n, n)``.

    Computed as ``𝔡∇w`` (vector version, matrix values column-wise) on the face template;
    evaluation ``a = faces[f,0]``, cut ``c = faces[f,2]``.
    """
    fn = "curvature_2form"
    _check_mesh_rot(edge_rot, mesh, fn)
    fe = mesh.face_edges.to(edge_rot.device)
    # pair_list(3) = (01, 02, 12) = (ab, ac, bc) = face_edges slots (2, 1, 0); all canonical (a<b<c)
    T = dense_simplex_transports(edge_rot[fe[:, [2, 1, 0]]], 3)
    tri = torch.tensor([[0, 1, 2]], dtype=torch.long, device=edge_rot.device)
    return unsymmetrized_vector(T, connection_form(T), tri, matrix_values=True).squeeze(-3)


def _mesh_pd_gather(tet_face_rot, face_edge_rot, edge_values, mesh, fn):
    """Per tet ``(T, 4, 3)`` slots: transports ``R_{c_t c_f} R_{c_f c_e}``, edge ids, coefficients."""
    Tn, F, E = mesh.tets.shape[0], mesh.faces.shape[0], mesh.edges.shape[0]
    n = edge_values.shape[-1] if edge_values.ndim == 2 else -1
    if tet_face_rot.shape != (Tn, 4, n, n):
        raise ValueError(f"{fn}: tet_face_rot must have shape (T, 4, n, n) = ({Tn}, 4, {n}, {n}), got {tuple(tet_face_rot.shape)}")
    if face_edge_rot.shape != (F, 3, n, n):
        raise ValueError(f"{fn}: face_edge_rot must have shape (F, 3, n, n) = ({F}, 3, {n}, {n}), got {tuple(face_edge_rot.shape)}")
    if edge_values.ndim != 2 or edge_values.shape[0] != E:
        raise ValueError(f"{fn}: edge_values must have shape (E, n) with E={E}, got {tuple(edge_values.shape)}")
    dev = edge_values.device
    tf = mesh.tet_faces.to(dev)
    fe = mesh.face_edges.to(dev)[tf]  # (T, 4, 3) edge ids
    coef = mesh.tet_face_signs.to(dev)[..., None] * mesh.face_edge_signs.to(dev)[tf]  # (T, 4, 3)
    return tf, fe, coef


def primal_dual_dd_mesh(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor,
                        mesh) -> torch.Tensor:
    """Primal-dual ``d∇d∇α`` on every tet of a mesh (Def. 4.2 twice): ``(T, n)`` at ``c_t``.

    Args:
        tet_face_rot: ``(T, 4, n, n)`` ``R_{c_t c_f}`` for ``f = mesh.tet_faces[t, k]``.
        face_edge_rot: ``(F, 3, n, n)`` ``R_{c_f c_e}`` for ``e = mesh.face_edges[f, m]``.
        edge_values: ``(E, n)`` at ``c_e``, canonical edge orientation ``mesh.edges``.
        mesh: :class:`torchconn.mesh.TetMesh` (incidence signs ``tet_face_signs``, ``face_edge_signs``).
    """
    fn = "primal_dual_dd_mesh"
    tf, _, _ = _mesh_pd_gather(tet_face_rot, face_edge_rot, edge_values, mesh, fn)
    dev = edge_values.device
    face_vals = primal_dual_face(face_edge_rot, edge_values[mesh.face_edges.to(dev)],
                                 mesh.face_edge_signs.to(dev))  # (F, n)
    return primal_dual_tet(tet_face_rot, face_vals[tf], mesh.tet_face_signs.to(dev))


def primal_dual_wedge_mesh(tet_face_rot: torch.Tensor, face_edge_rot: torch.Tensor, edge_values: torch.Tensor,
                           mesh) -> torch.Tensor:
    """Curvature-pair form ``Σ_(e,e') ⟨Ω,[c_fe, c_e, c_fe', c_t]⟩_{c_t}^{c_e} α_e`` on every tet: ``(T, n)``.

    Pairs the two slots (face, edge) of each tet edge by their combined incidence coefficient
    (``+1`` -> ``f_e``, ``-1`` -> ``f_e'``; ``α_e`` in canonical orientation carries the sign of
    the ``+1`` slot, which is ``+1`` by construction). Arguments as :func:`primal_dual_dd_mesh`.
    """
    fn = "primal_dual_wedge_mesh"
    tf, fe, coef = _mesh_pd_gather(tet_face_rot, face_edge_rot, edge_values, mesh, fn)
    Tn = tf.shape[0]
    path = (tet_face_rot.unsqueeze(-3) @ face_edge_rot[tf]).reshape(Tn, 12, *tet_face_rot.shape[-2:])
    fe, coef = fe.reshape(Tn, 12), coef.reshape(Tn, 12)
    # sort slots by (edge id, coefficient): each edge gives consecutive (-1, +1) slots
    key = fe * 2 + (coef > 0).long()
    order = torch.argsort(key, dim=1)
    path = torch.gather(path, 1, order[..., None, None].expand_as(path))
    fe_sorted = torch.gather(fe, 1, order)
    omega = path[:, 1::2] - path[:, 0::2]  # (T, 6, n, n): plus-prong minus minus-prong
    vals = edge_values[fe_sorted[:, 1::2]]  # (T, 6, n)
    return (omega @ vals.unsqueeze(-1)).squeeze(-1).sum(-2)
