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

Operators (docs/conventions.md §1, errata 1, 2, 4, 5, 6, 8)
-----------------------------------------------------------
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
  :func:`behs21_dd_solder`, :func:`wedge_solder`, :func:`primal_dual_dd_mesh`,
  :func:`primal_dual_wedge_mesh`.
"""
from __future__ import annotations

import itertools
import math
from functools import lru_cache

import torch

from ...mesh.simplex import FACE_EDGE_SIGNS, TET_FACE_SIGNS, TET_FACES

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
    "TET_FACES",
    "TET_FACE_SIGNS",
    "FACE_EDGE_SIGNS",
]

# ----------------------------------------------------------------------------- templates



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
            if tup.numel() and not torch.compiler.is_compiling() and (tup.min() < 0 or tup.max() >= s):
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
            if not torch.compiler.is_compiling() and (flat < 0).any():
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
    # a check of values: not while torch.compile traces (the label tables are then the library's own)
    if tuples.numel() and not torch.compiler.is_compiling() and (tuples.min() < 0 or tuples.max() >= s):
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
    (docs/conventions.md §1), every term in the fiber of ``x0``. Identical to the BEHS21 formula of Ch. 4.

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
    """Alternation of a Lie-algebra valued k-form, ``k <= 2`` (Ch. 5; docs/conventions.md §1).

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
