"""Exact elimination of sparse linear equality constraints with small dyadic coefficients.

The constraints of a seamless parametrization (transitions ``u_B = R u_A + t`` with ``R`` a
signed permutation, boundary / singular / feature coordinates equal to integer unknowns, one
pinned point) have coefficients ``0, ±1`` and, after substitution, ``±1/2`` or ``±2`` at half-turn
singular edges: dyadic rationals that float64 represents exactly. So the elimination is exact:
every row is reduced by substituting the variables eliminated before it; an empty row is
redundant (or, with a non-zero constant, contradictory: reported, never silently dropped); a
non-empty row eliminates one of its variables (its *pivot*).

Pivot rule (as CoMISo's constrained solver): a continuous variable if the row has one (the one
with the largest index); else an integer variable ``p`` such that every other coefficient and
the constant are integer multiples of its own (so ``x_p`` stays an integer combination of the
remaining integer unknowns: ``2 m - t_a - t_b = 0`` at a half turn keeps ``t_a = 2 m - t_b``);
else the integer variable with the smallest coefficient, whose integrality is then only implied
(listed in :attr:`Elimination.relaxed_integers`).

The result expresses every variable as ``x = Z y + z0`` in the free variables ``y`` (those never
eliminated), with ``Z`` sparse. Substitution caches fully resolved expressions (path
compression), so chains of eliminations stay short.

One-time combinatorial setup: the rows are processed in a Python loop (a few microseconds each).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from .pivot_rule import _integer_rule, _sequential

__all__ = ["ConstraintRows", "Elimination", "eliminate"]


class ConstraintRows:
    """A list of rows ``sum_k coef_k x_{var_k} + const = 0`` with a label per row.

    ``add(vars, coefs, const, label)``: ``vars`` and ``coefs`` sequences of equal length.
    ``add_many(vars (N, k), coefs (N, k), const (N,), label)``: ``N`` rows of ``k`` terms each,
    stored as one block of arrays (no Python work per row). Zero coefficients are kept as given
    and ignored by the elimination.
    """

    def __init__(self) -> None:
        self._blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        self.labels: list[str] = []
        self._n = 0

    def add(self, vars, coefs, const: float = 0.0, label: str = "") -> None:
        v = np.asarray([int(x) for x in vars], np.int64).reshape(1, -1)
        c = np.asarray([float(x) for x in coefs], np.float64).reshape(1, -1)
        if v.shape != c.shape:
            raise ValueError(f"a row needs one coefficient per variable, got {v.shape[1]} and {c.shape[1]}")
        self._append(v, c, np.array([float(const)]), label)

    def add_many(self, vars, coefs, const=None, label: str = "") -> None:
        vars = np.asarray(vars, np.int64)
        coefs = np.broadcast_to(np.asarray(coefs, np.float64), vars.shape)
        const = np.zeros(vars.shape[0]) if const is None else np.broadcast_to(np.asarray(const, np.float64), vars.shape[:1])
        self._append(vars, coefs, const, label)

    def _append(self, v, c, k, label) -> None:
        self._blocks.append((v, np.array(c, np.float64), np.array(k, np.float64), self._label_index(label)))
        self._n += v.shape[0]

    def _label_index(self, label: str) -> int:
        try:
            return self.labels.index(label)
        except ValueError:
            self.labels.append(label)
            return len(self.labels) - 1

    def label_index(self) -> np.ndarray:
        """``(R,)`` index into :attr:`labels` of every row."""
        return np.concatenate([np.full(v.shape[0], li, np.int64) for v, _, _, li in self._blocks] or
                              [np.zeros(0, np.int64)])

    def label(self, row: int) -> str:
        return self.labels[int(self.label_index()[row])]

    def coo(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(row (nnz,), var (nnz,), coef (nnz,), const (R,))`` of every term (zeros included)."""
        ri, vi, ci, ks = [], [], [], []
        start = 0
        for v, c, k, _ in self._blocks:
            n, w = v.shape
            ri.append(np.repeat(np.arange(start, start + n), w))
            vi.append(v.reshape(-1))
            ci.append(c.reshape(-1))
            ks.append(k)
            start += n
        cat = (lambda a, dt: np.concatenate(a) if a else np.zeros(0, dt))  # noqa: E731
        return cat(ri, np.int64), cat(vi, np.int64), cat(ci, np.float64), cat(ks, np.float64)

    @property
    def rows(self) -> list[tuple[tuple, tuple, float]]:
        """The rows as ``(vars, coefs, const)`` tuples (for the per-row reference)."""
        out = []
        for v, c, k, _ in self._blocks:
            out += [(tuple(a), tuple(b), kk) for a, b, kk in zip(v.tolist(), c.tolist(), k.tolist())]
        return out

    def __len__(self) -> int:
        return self._n


@dataclass
class Elimination:
    """Every variable as ``x = Z @ y + z0`` in the free variables ``y``.

    Attributes:
        n_vars: number of variables ``n``.
        free: ``(m,)`` int64, the free variables (ascending); ``y[j]`` is variable ``free[j]``.
        Z: ``(n, m)`` CSR matrix, ``z0 (n,)`` float64.
        is_int: ``(n,)`` bool, the integer variables (as declared).
        free_is_int: ``(m,)`` bool.
        redundant: number of rows that reduced to ``0 = 0``.
        conflicts: ``[(row, label, residual)]`` rows that reduced to ``c = 0`` with ``c != 0``.
        relaxed_integers: integer variables eliminated with a non-unit coefficient (their
            integrality is not implied by integer free variables).
    """

    n_vars: int
    free: np.ndarray
    Z: sp.csr_matrix
    z0: np.ndarray
    is_int: np.ndarray
    free_is_int: np.ndarray
    redundant: int
    conflicts: list = field(default_factory=list)
    relaxed_integers: list = field(default_factory=list)

    def expand(self, y: np.ndarray) -> np.ndarray:
        """All variables ``Z y + z0`` from the free ones ``y (m,)`` or ``(m, k)``."""
        out = self.Z @ y
        return out + (self.z0 if out.ndim == 1 else self.z0[:, None])


def eliminate_reference(rows: ConstraintRows, n_vars: int, is_int: np.ndarray, *, order=None) -> Elimination:
    """The per-row elimination (module docstring), row by row with dictionaries: the reference that
    :func:`eliminate` equals (tests), and its rule. Same arguments and result."""
    is_int = np.asarray(is_int, bool)
    if is_int.shape != (n_vars,):
        raise ValueError(f"is_int must have shape ({n_vars},), got {is_int.shape}")
    seq = range(len(rows)) if order is None else order
    all_rows = rows.rows
    labels = rows.label_index()
    expr, resolve, redundant, conf, relaxed, _ = _sequential(((r, *all_rows[r]) for r in seq), is_int)
    conflicts = [(r, rows.labels[labels[r]], c) for r, c in conf]

    # final: every variable in the free ones
    eliminated = np.zeros(n_vars, bool)
    if expr:
        eliminated[np.fromiter(expr.keys(), np.int64, len(expr))] = True
    free = np.nonzero(~eliminated)[0]
    col = np.full(n_vars, -1, np.int64)
    col[free] = np.arange(free.size)
    ri, ci, vals = [free], [col[free]], [np.ones(free.size)]
    z0 = np.zeros(n_vars)
    er, ec, ev = [], [], []
    for v in expr:
        terms, c = resolve(v)
        z0[v] = c
        for z, b in terms.items():
            er.append(v)
            ec.append(col[z])
            ev.append(b)
    ri.append(np.asarray(er, np.int64))
    ci.append(np.asarray(ec, np.int64))
    vals.append(np.asarray(ev, np.float64))
    Z = sp.csr_matrix((np.concatenate(vals), (np.concatenate(ri), np.concatenate(ci))), shape=(n_vars, free.size))
    return Elimination(n_vars=n_vars, free=free, Z=Z, z0=z0, is_int=is_int, free_is_int=is_int[free],
                       redundant=redundant, conflicts=conflicts, relaxed_integers=sorted(set(relaxed)))


# ----------------------------------------------------------------------------- the fast path
def _gather(indptr: np.ndarray, indices: np.ndarray, nodes: np.ndarray):
    """``(owner, neighbour position)`` of every CSR entry of the rows ``nodes``."""
    lens = indptr[nodes + 1] - indptr[nodes]
    starts = np.repeat(indptr[nodes], lens)
    offs = np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens)
    return np.repeat(nodes, lens), starts + offs


def _scale_rows(s: np.ndarray) -> sp.dia_matrix:
    return sp.diags(np.asarray(s, np.float64))


def eliminate(rows: ConstraintRows, n_vars: int, is_int: np.ndarray, *, order=None) -> Elimination:
    """Eliminate ``rows`` (a :class:`ConstraintRows`) over ``n_vars`` variables: the result of the
    per-row rule (module docstring, :func:`eliminate_reference`), computed in bulk.

    The continuous variables are eliminated in array operations; only the rows left over the
    integers run the per-row rule. Why that is the same result: a row whose reduced form keeps a
    continuous variable pivots on its largest one, so which continuous variables stay free and
    their expressions do not depend on the row order (the reduced row echelon form of the
    constraints, continuous columns first, is unique); the rule's order matters only among the
    rows that reduce to integers alone (``q_k``), and each of those is fixed modulo the integer
    rows before it, which the per-row rule substitutes away. So:

    1. *links* (rows with two continuous terms of equal magnitude, ``x_u = ±x_v +`` integers: the
       transitions across cut faces) form a graph over the continuous variables; its minimum
       spanning forest by row index is the forest of the rows that merged two components when
       they came (Kruskal's order); every variable is ``sigma_v x_root + P_v`` along it (``P_v``:
       integers and a constant, accumulated per breadth-first level), the root of a component
       its smallest variable (the per-row rule keeps the smaller of two merged representatives);
       a link off the forest gives the integer row ``q_k = a_u P_u + a_v P_v + (its integers)``;
    2. *anchors* (one continuous term: boundary planes, singular and feature lines, corners, the
       pin) after every link of their component: the first determines the root, the others give
       integer rows;
    3. a component where that does not hold (a link cycle that flips the sign, an anchor before
       one of its links, a row with more continuous terms) runs the per-row rule over its rows
       with the integers kept as symbols (few rows: half-turn singular vertices);
    4. the integer rows, in row order, run the per-row rule (:func:`_sequential`);
    5. every variable in the free ones: one sparse product.

    With dyadic coefficients (those of a seamless problem) every sum is exact, so ``Z`` and
    ``z0`` equal :func:`eliminate_reference`'s bit for bit (tests on random systems and on the
    HexMe problems). Cost: array operations over the rows plus the per-row rule over the integer
    rows (on the 1M-tet ``i02c_m2@lmax=0.14``: docs/results/hexmesh.md).

    Args:
        rows: the constraints.
        n_vars: number of variables.
        is_int: ``(n_vars,)`` bool, integer variables.
        order: optional row order (indices), default the order they were added.
    """
    is_int = np.asarray(is_int, bool)
    if is_int.shape != (n_vars,):
        raise ValueError(f"is_int must have shape ({n_vars},), got {is_int.shape}")
    n = n_vars
    ri, vi, ci, const = rows.coo()
    if vi.size and (vi.min() < 0 or vi.max() >= n):
        raise ValueError(f"a row refers to a variable outside [0, {n})")
    R0 = len(rows)
    M = sp.csr_matrix((ci, (ri, vi)), shape=(R0, n))  # duplicates summed
    rid = np.arange(R0)
    if order is not None:
        rid = np.asarray(order, np.int64).reshape(-1)
        M = M[rid]
    kappa = const[rid]
    M.sum_duplicates()
    M.eliminate_zeros()
    M = M.tocsr()
    R = M.shape[0]
    cont = ~is_int
    row_of = np.repeat(np.arange(R), np.diff(M.indptr))
    ec = cont[M.indices]
    nc = np.bincount(row_of[ec], minlength=R)
    # KK: each row's integer terms and its constant (column n)
    Mi = M.multiply(is_int[None, :].astype(np.float64)).tocsr()
    KK = sp.hstack([Mi, sp.csr_matrix(kappa[:, None])], format="csr")
    KK.eliminate_zeros()
    # the continuous terms of each row, first and second
    pos = np.nonzero(ec)[0]
    prow = row_of[pos]
    starts = np.r_[True, prow[1:] != prow[:-1]] if pos.size else np.zeros(0, bool)
    first = np.full(R, -1, np.int64)
    first[prow[starts]] = pos[starts]
    is_second = np.r_[False, ~starts[1:] & starts[:-1]] if pos.size else np.zeros(0, bool)
    second = np.full(R, -1, np.int64)
    second[prow[is_second]] = pos[is_second]
    link = (nc == 2) & (np.abs(M.data[np.maximum(first, 0)]) == np.abs(M.data[np.maximum(second, 0)]))
    anchor = nc == 1
    general = (nc >= 2) & ~link
    lk = np.nonzero(link)[0]
    lu, lv = M.indices[first[lk]], M.indices[second[lk]]
    au, av = M.data[first[lk]], M.data[second[lk]]

    # ---- components of the continuous variables (links and general rows)
    gpos = pos[general[prow]]
    grow = row_of[gpos]
    same = np.r_[grow[1:] == grow[:-1], False] if gpos.size else np.zeros(0, bool)
    ga = M.indices[gpos[:-1][same[:-1]]] if gpos.size > 1 else np.zeros(0, np.int64)
    gb = M.indices[gpos[1:][same[:-1]]] if gpos.size > 1 else np.zeros(0, np.int64)
    ea, eb = np.r_[lu, ga], np.r_[lv, gb]
    adj = sp.coo_matrix((np.ones(ea.size, np.int8), (ea, eb)), shape=(n, n))
    _, comp = connected_components(adj, directed=False)

    # ---- minimum spanning forest of the links by row index (Kruskal's order)
    a_, b_ = np.minimum(lu, lv), np.maximum(lu, lv)
    key = a_ * n + b_
    o = np.lexsort((lk, key))
    firstpair = np.r_[True, key[o][1:] != key[o][:-1]] if o.size else np.zeros(0, bool)
    cand = o[firstpair]  # the earliest link of each pair of variables
    W = sp.coo_matrix((lk[cand] + 1.0, (a_[cand], b_[cand])), shape=(n, n)).tocsr()
    T = minimum_spanning_tree(W).tocoo()
    tree_row = np.round(T.data).astype(np.int64) - 1  # row of each forest edge
    in_tree = np.zeros(R, bool)
    in_tree[tree_row] = True
    # breadth-first levels from each component's smallest variable: sigma_v, P_v (n x (n+1))
    _, fcomp = connected_components(T, directed=False)
    root = np.zeros(n, bool)
    cont_idx = np.nonzero(cont)[0]
    fc = fcomp[cont_idx]
    firsts = np.unique(fc, return_index=True)[1]  # cont_idx ascending: the smallest variable first
    root[cont_idx[firsts]] = True
    ta, tb = T.row, T.col
    A = sp.csr_matrix((np.r_[tree_row, tree_row] + 1, (np.r_[ta, tb], np.r_[tb, ta])), shape=(n, n))
    link_u = np.full(R, -1, np.int64)
    link_v = np.full(R, -1, np.int64)
    link_au = np.zeros(R)
    link_av = np.zeros(R)
    link_u[lk], link_v[lk], link_au[lk], link_av[lk] = lu, lv, au, av
    sigma = np.zeros(n)
    level = np.full(n, -1, np.int64)
    frontier = np.nonzero(root)[0]
    sigma[frontier] = 1.0
    level[frontier] = 0
    blocks_nodes = [frontier]
    blocks_P = [sp.csr_matrix((frontier.size, n + 1))]
    prev_pos = np.zeros(n, np.int64)
    prev_pos[frontier] = np.arange(frontier.size)
    Pprev = blocks_P[0]
    depth = 0
    while frontier.size:
        owner, ent = _gather(A.indptr, A.indices, frontier)
        child = A.indices[ent]
        erow = A.data[ent].astype(np.int64) - 1
        keep = level[child] == -1
        owner, child, erow = owner[keep], child[keep], erow[keep]
        if not child.size:
            break
        depth += 1
        a_c = np.where(link_u[erow] == child, link_au[erow], link_av[erow])
        a_p = np.where(link_u[erow] == child, link_av[erow], link_au[erow])
        s = -a_p / a_c
        sigma[child] = s * sigma[owner]
        level[child] = depth
        Pnew = (_scale_rows(s) @ Pprev[prev_pos[owner]] - _scale_rows(1.0 / a_c) @ KK[erow]).tocsr()
        blocks_nodes.append(child)
        blocks_P.append(Pnew)
        prev_pos[child] = np.arange(child.size)
        Pprev = Pnew
        frontier = child
    nodes = np.concatenate(blocks_nodes)
    Pst = sp.vstack(blocks_P, format="csr")
    perm = sp.csr_matrix((np.ones(nodes.size), (nodes, np.arange(nodes.size))), shape=(n, nodes.size))
    P = (perm @ Pst).tocsr()  # row v: P_v (zero for integer variables and roots)
    rootvar = np.zeros(n, np.int64)  # the root of each continuous variable's forest component
    rootvar[cont_idx] = cont_idx[firsts][np.searchsorted(np.unique(fc), fc)]

    # ---- components handled in bulk (easy) or by the per-row rule (hard)
    ncomp = comp.max(initial=-1) + 1
    hard = np.zeros(ncomp, bool)
    hard[comp[M.indices[gpos]]] = True
    off = np.nonzero(link & ~in_tree)[0]
    ou, ov = link_u[off], link_v[off]
    flip = link_au[off] * sigma[ou] + link_av[off] * sigma[ov] != 0
    hard[comp[ou[flip]]] = True
    last_link = np.full(ncomp, -1, np.int64)
    np.maximum.at(last_link, comp[lu], lk)
    an = np.nonzero(anchor)[0]
    avar = M.indices[first[an]]
    acoef = M.data[first[an]]
    acomp = comp[avar]
    hard[acomp[an < last_link[acomp]]] = True
    row_comp = np.full(R, -1, np.int64)
    has_c = nc > 0
    row_comp[has_c] = comp[M.indices[first[has_c]]]
    row_hard = has_c & hard[np.maximum(row_comp, 0)]

    # integer rows q_k (sparse over the variables and the constant), with their row index
    q_rows, q_mats = [], []
    zero_int = np.nonzero(nc == 0)[0]
    q_rows.append(zero_int)
    q_mats.append(KK[zero_int])
    eo = off[~row_hard[off]]
    q_rows.append(eo)
    q_mats.append((_scale_rows(link_au[eo]) @ P[link_u[eo]] + _scale_rows(link_av[eo]) @ P[link_v[eo]]
                   + KK[eo]).tocsr())
    ea_ = ~row_hard[an]
    an_e, avar_e, acoef_e, acomp_e = an[ea_], avar[ea_], acoef[ea_], acomp[ea_]
    o2 = np.lexsort((an_e, acomp_e))
    lead = np.r_[True, acomp_e[o2][1:] != acomp_e[o2][:-1]] if o2.size else np.zeros(0, bool)
    head = o2[lead]  # the first anchor of each easy component: it determines the root
    D_of_comp = np.full(ncomp, -1, np.int64)
    D_of_comp[acomp_e[head]] = np.arange(head.size)
    hv, ha = avar_e[head], acoef_e[head]
    D = (-(_scale_rows(1.0 / (ha * sigma[hv])) @ (_scale_rows(ha) @ P[hv] + KK[an_e[head]]))).tocsr()
    rest = o2[~lead]
    rv, ra = avar_e[rest], acoef_e[rest]
    q_rows.append(an_e[rest])
    q_mats.append((_scale_rows(ra * sigma[rv]) @ D[D_of_comp[acomp_e[rest]]] + _scale_rows(ra) @ P[rv]
                   + KK[an_e[rest]]).tocsr())

    # ---- hard components: the per-row rule with the integers as symbols
    hr = np.nonzero(row_hard)[0]
    ind, dat = M.indices, M.data
    hexpr, hresolve, _, _, _, emitted = _sequential(
        ((int(r), ind[M.indptr[r]:M.indptr[r + 1]].tolist(), dat[M.indptr[r]:M.indptr[r + 1]].tolist(),
          float(kappa[r])) for r in hr), is_int, opaque=is_int)

    # ---- the integer rows in row order: the per-row rule
    Q = sp.vstack(q_mats, format="csr")
    Q.eliminate_zeros()
    Q.sort_indices()
    qr = np.concatenate(q_rows)
    # the constant is column n, the last of each sorted row
    has_c = np.zeros(Q.shape[0], bool)
    nz = np.diff(Q.indptr) > 0
    has_c[nz] = Q.indices[Q.indptr[1:][nz] - 1] == n
    qc = np.zeros(Q.shape[0])
    qc[has_c] = Q.data[Q.indptr[1:][has_c] - 1]
    ends = Q.indptr[1:] - has_c
    qi, qd, qs, qe = Q.indices.tolist(), Q.data.tolist(), Q.indptr[:-1].tolist(), ends.tolist()
    qcl, qrl = qc.tolist(), qr.tolist()
    items = [(qrl[k], qi[qs[k]:qe[k]], qd[qs[k]:qe[k]], qcl[k]) for k in np.argsort(qr, kind="stable").tolist()]
    if emitted:
        items += [(r, list(terms), list(terms.values()), c) for r, terms, c in emitted]
        items.sort(key=lambda it: it[0])
    iexpr, iresolve, redundant, conf, relaxed = _integer_rule(items)
    conflicts = [(int(rid[r]), rows.labels[rows.label_index()[rid[r]]], c) for r, c in conf]

    # ---- every variable in the free ones
    easy_c = cont & ~hard[comp]
    anchored = np.zeros(n, bool)
    anchored[easy_c] = D_of_comp[comp[easy_c]] >= 0
    eliminated = np.zeros(n, bool)
    eliminated[easy_c] = (~root[easy_c]) | anchored[easy_c]
    for v in hexpr:
        eliminated[v] = True
    for v in iexpr:
        eliminated[v] = True
    free = np.nonzero(~eliminated)[0]
    # X: continuous variables over (free continuous, integers, constant); integers: themselves
    fr = np.nonzero(easy_c & ~anchored)[0]
    Xf = sp.csr_matrix((sigma[fr], (fr, rootvar[fr])), shape=(n, n + 1)) + perm_rows(P, fr, n)
    fa = np.nonzero(anchored)[0]
    Xa = (_scale_rows(sigma[fa]) @ D[D_of_comp[comp[fa]]] + P[fa]).tocsr()
    Xa = perm_rows(Xa, fa, n, compact=True)
    hr_, hc_, hv_ = [], [], []
    for v in hexpr:
        terms, c = hresolve(v)
        for z, b in terms.items():
            hr_.append(v)
            hc_.append(z)
            hv_.append(b)
        if c != 0.0:
            hr_.append(v)
            hc_.append(n)
            hv_.append(c)
    hcf = [v for v in np.nonzero(cont & hard[comp])[0].tolist() if v not in hexpr]
    ident = np.r_[np.nonzero(is_int)[0], np.asarray(hcf, np.int64)]
    X = (Xf + Xa + sp.csr_matrix((hv_, (hr_, hc_)), shape=(n, n + 1))
         + sp.csr_matrix((np.ones(ident.size), (ident, ident)), shape=(n, n + 1))).tocsr()
    # substitution of the integers: S (n+1, n+1)
    sr, sc, sv = [], [], []
    for v in iexpr:
        terms, c = iresolve(v)
        for z, b in terms.items():
            sr.append(v)
            sc.append(z)
            sv.append(b)
        if c != 0.0:
            sr.append(v)
            sc.append(n)
            sv.append(c)
    keep = np.ones(n + 1, bool)
    if iexpr:
        keep[np.fromiter(iexpr.keys(), np.int64, len(iexpr))] = False
    kk = np.nonzero(keep)[0]
    S = sp.csr_matrix((np.r_[np.asarray(sv, np.float64), np.ones(kk.size)],
                       (np.r_[np.asarray(sr, np.int64), kk], np.r_[np.asarray(sc, np.int64), kk])), shape=(n + 1, n + 1))
    Fin = (X @ S).tocsc()
    Fin.eliminate_zeros()
    z0 = np.asarray(Fin[:, n].todense()).reshape(-1)
    Z = Fin[:, free].tocsr()
    Z.eliminate_zeros()
    Z.sort_indices()
    return Elimination(n_vars=n, free=free, Z=Z, z0=z0, is_int=is_int, free_is_int=is_int[free],
                       redundant=redundant, conflicts=conflicts, relaxed_integers=sorted(set(relaxed)))


def perm_rows(B: sp.csr_matrix, rows_: np.ndarray, n: int, compact: bool = False) -> sp.csr_matrix:
    """``(n, B.shape[1])``: row ``rows_[k]`` is row ``k`` of ``B`` (``compact``) or row
    ``rows_[k]`` of ``B`` (else); the other rows zero."""
    src = np.arange(rows_.size) if compact else rows_
    sel = sp.csr_matrix((np.ones(rows_.size), (rows_, src)), shape=(n, B.shape[0]))
    return (sel @ B).tocsr()
