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

__all__ = ["ConstraintRows", "Elimination", "eliminate"]


class ConstraintRows:
    """A list of rows ``sum_k coef_k x_{var_k} + const = 0`` with a label per row.

    ``add(vars, coefs, const, label)``: ``vars`` and ``coefs`` sequences of equal length.
    ``add_many(vars (N, k), coefs (N, k), const (N,), label)``: ``N`` rows of ``k`` terms each
    (zero coefficients are dropped).
    """

    def __init__(self) -> None:
        self.rows: list[tuple[tuple, tuple, float]] = []
        self.labels: list[str] = []
        self._label_of: list[int] = []

    def add(self, vars, coefs, const: float = 0.0, label: str = "") -> None:
        self.rows.append((tuple(int(v) for v in vars), tuple(float(c) for c in coefs), float(const)))
        self._label_of.append(self._label_index(label))

    def add_many(self, vars, coefs, const=None, label: str = "") -> None:
        vars = np.asarray(vars, np.int64)
        coefs = np.broadcast_to(np.asarray(coefs, np.float64), vars.shape)
        const = np.zeros(vars.shape[0]) if const is None else np.broadcast_to(np.asarray(const, np.float64), vars.shape[:1])
        li = self._label_index(label)
        for v, c, k in zip(vars.tolist(), coefs.tolist(), const.tolist()):
            self.rows.append((tuple(v), tuple(c), k))
            self._label_of.append(li)

    def _label_index(self, label: str) -> int:
        try:
            return self.labels.index(label)
        except ValueError:
            self.labels.append(label)
            return len(self.labels) - 1

    def label(self, row: int) -> str:
        return self.labels[self._label_of[row]]

    def __len__(self) -> int:
        return len(self.rows)


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


def eliminate(rows: ConstraintRows, n_vars: int, is_int: np.ndarray, *, order=None) -> Elimination:
    """Eliminate ``rows`` (a :class:`ConstraintRows`) over ``n_vars`` variables (module docstring).

    Args:
        rows: the constraints.
        n_vars: number of variables.
        is_int: ``(n_vars,)`` bool, integer variables.
        order: optional row order (indices), default the order they were added.
    """
    is_int = np.asarray(is_int, bool)
    if is_int.shape != (n_vars,):
        raise ValueError(f"is_int must have shape ({n_vars},), got {is_int.shape}")
    expr: dict[int, tuple[dict, float]] = {}  # eliminated var -> (terms, const), possibly stale
    redundant = 0
    conflicts = []
    relaxed = []

    def stale(terms: dict) -> bool:
        return any(w in expr for w in terms)

    def resolve(v: int) -> tuple[dict, float]:
        # iterative path compression: resolve what v's expression depends on first, then v; the
        # eliminations are acyclic (a pivot's expression holds only variables free at the time)
        if not stale(expr[v][0]):
            return expr[v]
        stack = [v]
        while stack:
            u = stack[-1]
            terms, c = expr[u]
            pending = [w for w in terms if w in expr and stale(expr[w][0])]
            if pending:
                stack.extend(pending)
                continue
            stack.pop()
            if not stale(terms):
                continue
            out: dict[int, float] = {}
            cc = c
            for w, a in terms.items():
                if w in expr:
                    tw, cw = expr[w]
                    for z, b in tw.items():
                        out[z] = out.get(z, 0.0) + a * b
                    cc += a * cw
                else:
                    out[w] = out.get(w, 0.0) + a
            expr[u] = ({z: b for z, b in out.items() if b != 0.0}, cc)
        return expr[v]

    seq = range(len(rows)) if order is None else order
    for r in seq:
        vars_, coefs, const = rows.rows[r]
        red: dict[int, float] = {}
        c = const
        for v, a in zip(vars_, coefs):
            if a == 0.0:
                continue
            if v in expr:
                tv, cv = resolve(v)
                for z, b in tv.items():
                    red[z] = red.get(z, 0.0) + a * b
                c += a * cv
            else:
                red[v] = red.get(v, 0.0) + a
        red = {z: b for z, b in red.items() if b != 0.0}
        if not red:
            if c != 0.0:
                conflicts.append((r, rows.label(r), c))
            else:
                redundant += 1
            continue
        cont = [z for z in red if not is_int[z]]
        if cont:
            p = max(cont)
        else:
            # an integer pivot whose expression keeps integer coefficients and constant
            def integral(z):
                a = red[z]
                return float(c / a).is_integer() and all(float(b / a).is_integer() for b in red.values())

            good = [z for z in red if integral(z)]
            if good:
                p = max(good)
            else:
                p = min(red, key=lambda z: (abs(red[z]), -z))
                relaxed.append(p)
        a_p = red.pop(p)
        expr[p] = ({z: -b / a_p for z, b in red.items()}, -c / a_p)

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
