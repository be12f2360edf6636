"""The per-row pivot rule of the exact constraint elimination (:mod:`.elimination`'s docstring).

:func:`_sequential` reduces rows one after another (substituting the variables eliminated before
each, path-compressed) and pivots each by the rule: a continuous variable if the row has one,
else an integer one whose expression stays integral (:func:`_integer_pivot`), else the smallest
coefficient (relaxed). :func:`_integer_rule` is the same rule for rows over integer variables
only. :func:`~.elimination.eliminate_reference` runs it on every row;
:func:`~.elimination.eliminate` only on the rows its bulk path leaves.
"""
from __future__ import annotations

import numpy as np

__all__: list[str] = []


def _integer_pivot(red: dict, c: float, relaxed: list) -> int:
    """The pivot of an all-integer row ``sum_z red[z] y_z = c``: the largest unknown whose
    expression keeps integer coefficients and constant, else the smallest coefficient (that
    unknown is relaxed: appended to ``relaxed``)."""
    def integral(z):
        a = red[z]
        return float(c / a).is_integer() and all(float(b / a).is_integer() for b in red.values())

    good = [z for z in red if integral(z)]
    if good:
        return max(good)
    p = min(red, key=lambda z: (abs(red[z]), -z))
    relaxed.append(p)
    return p


def _sequential(row_iter, is_int: np.ndarray, opaque: np.ndarray | None = None):
    """The per-row elimination (module docstring) of the rows ``(r, vars, coefs, const)`` of
    ``row_iter``, in that order, with dictionaries.

    ``opaque (n,)`` bool: variables never substituted nor pivoted (symbols); then a row whose
    reduced form has no other variable is not counted but returned in ``emitted`` as
    ``(r, terms, const)``, and the pivot is the largest other variable.

    Returns ``(expr, resolve, redundant, conflicts [(r, residual)], relaxed, emitted)``: ``expr``
    maps each eliminated variable to its (possibly stale) ``(terms, const)``, ``resolve(v)`` its
    expression in the free variables.
    """
    expr: dict[int, tuple[dict, float]] = {}  # eliminated var -> (terms, const), possibly stale
    redundant = 0
    conflicts = []
    relaxed = []
    emitted = []

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

    for r, vars_, coefs, const in row_iter:
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
        if opaque is not None:
            piv = [z for z in red if not opaque[z]]
            if not piv:
                emitted.append((r, red, c))
                continue
            p = max(piv)
        elif not red:
            if c != 0.0:
                conflicts.append((r, c))
            else:
                redundant += 1
            continue
        else:
            cont = [z for z in red if not is_int[z]]
            p = max(cont) if cont else _integer_pivot(red, c, relaxed)
        a_p = red.pop(p)
        expr[p] = ({z: -b / a_p for z, b in red.items()}, -c / a_p)
    return expr, resolve, redundant, conflicts, relaxed, emitted


def _integer_rule(items):
    """:func:`_sequential` for rows over integer variables only: the same rule and result (exact
    for dyadic coefficients), faster where the rows are simple. A variable eliminated by a
    single term with coefficient ``±1`` (``x_p = ±x_q + c``, most rows: equal translations, equal
    boundary planes) is an *alias*, kept in a union-find with path compression; the others keep
    a dictionary expression, resolved lazily. A row of two free variables is reduced without
    lookups, and a reduced row whose coefficients are all ``±1`` with an integer constant pivots
    on its largest variable (every variable passes the integral test).

    Returns ``(eliminated {v: None}, resolve, redundant, conflicts [(r, residual)], relaxed)``.
    """
    alias: dict[int, tuple[float, int, float]] = {}  # x_v = s x_t + c
    expr: dict[int, tuple[dict, float]] = {}  # x_v = terms . x + c (possibly stale)
    redundant = 0
    conflicts = []
    relaxed = []

    def find(v: int) -> tuple[float, int, float]:
        chain = []
        u = v
        while u in alias:
            chain.append(u)
            u = alias[u][1]
        s_acc, c_acc = 1.0, 0.0
        for w in reversed(chain):
            s, _, c = alias[w]
            s_acc, c_acc = s * s_acc, s * c_acc + c
            alias[w] = (s_acc, u, c_acc)
        return alias[v]

    def stale(terms: dict) -> bool:
        return any(w in alias or w in expr for w in terms)

    def gen_dep(w: int):
        if w in expr:
            return w
        if w in alias:
            r = find(w)[1]
            return r if r in expr else None
        return None

    def resolve_gen(v: int) -> tuple[dict, float]:
        if not stale(expr[v][0]):
            return expr[v]
        stack = [v]
        while stack:
            u = stack[-1]
            terms, c = expr[u]
            pending = [g for g in (gen_dep(w) for w in terms) if g is not None and stale(expr[g][0])]
            if pending:
                stack.extend(pending)
                continue
            stack.pop()
            if not stale(terms):
                continue
            out: dict[int, float] = {}
            cc = c
            for w, a in terms.items():
                if w in alias:
                    sw, r, kw = find(w)
                    cc += a * kw
                    if r in expr:
                        tr, cr = expr[r]
                        for z, b in tr.items():
                            out[z] = out.get(z, 0.0) + a * (sw * b)
                        cc += a * (sw * cr)
                    else:
                        out[r] = out.get(r, 0.0) + a * sw
                elif w in expr:
                    tw, cw = expr[w]
                    for z, b in tw.items():
                        out[z] = out.get(z, 0.0) + a * b
                    cc += a * cw
                else:
                    out[w] = out.get(w, 0.0) + a
            expr[u] = ({z: b for z, b in out.items() if b != 0.0}, cc)
        return expr[v]

    def resolve(v: int) -> tuple[dict, float]:
        if v in expr:
            return resolve_gen(v)
        s, r, c = find(v)
        if r in expr:
            tr, cr = resolve_gen(r)
            return {z: s * b for z, b in tr.items()}, s * cr + c
        return {r: s}, c

    for r, vars_, coefs, c in items:
        if (len(vars_) == 2 and vars_[0] != vars_[1] and vars_[0] not in alias and vars_[0] not in expr
                and vars_[1] not in alias and vars_[1] not in expr):
            red = {vars_[0]: coefs[0], vars_[1]: coefs[1]}
        else:
            red = {}
            for v, a in zip(vars_, coefs):
                if a == 0.0:
                    continue
                if v in alias:
                    sv, rv, kv = find(v)
                    c += a * kv
                    if rv in expr:
                        tv, cv = resolve_gen(rv)
                        for z, b in tv.items():
                            red[z] = red.get(z, 0.0) + a * (sv * b)
                        c += a * (sv * cv)
                    else:
                        red[rv] = red.get(rv, 0.0) + a * sv
                elif v in expr:
                    tv, cv = resolve_gen(v)
                    for z, b in tv.items():
                        red[z] = red.get(z, 0.0) + a * b
                    c += a * cv
                else:
                    red[v] = red.get(v, 0.0) + a
        red = {z: b for z, b in red.items() if b != 0.0}
        if not red:
            if c != 0.0:
                conflicts.append((r, c))
            else:
                redundant += 1
            continue
        if float(c).is_integer() and all(b == 1.0 or b == -1.0 for b in red.values()):
            p = max(red)
        else:
            p = _integer_pivot(red, c, relaxed)
        a_p = red.pop(p)
        if len(red) == 1:
            (z, b), = red.items()
            if b == a_p or b == -a_p:
                alias[p] = (-b / a_p, z, -c / a_p)
                continue
        expr[p] = ({z: -b / a_p for z, b in red.items()}, -c / a_p)
    eliminated = dict.fromkeys(alias)
    eliminated.update(dict.fromkeys(expr))
    return eliminated, resolve, redundant, conflicts, relaxed
