"""Quantization of the seamless map's integer unknowns: rounding (injective or greedy), stiffening, snapping.

Greedy multiple rounding (Bommes, Zimmer, Kobbelt 2009; HEXMESH.md step 6): solve the
continuous problem; sort the unfixed integer unknowns by their distance to the nearest integer;
round the closest ones while the summed rounding stays ``<= batch_error`` (at least one per
step); re-solve with them fixed; repeat. The re-solves reuse **one** factorization: with
``A y = b`` the continuous optimum and ``C = (A^{-1})_{II}`` the block of the inverse on the
integer unknowns ``I``, fixing a set ``B`` to values ``n_B`` moves the others to
``y_I + C_{IB} C_{BB}^{-1} (n_B - y_B)`` and leaves ``C - C_{IB} C_{BB}^{-1} C_{BI}`` (the
conditional mean and covariance of the Gaussian ``exp(-E)``): a dense update of size ``|I|``,
after ``|I|`` solves against the factor (batched right-hand sides). The continuous unknowns are
solved once at the end with every integer fixed. Where ``|I|^2`` would pass a memory budget
(large meshes) the rounding goes in blocks by distance thresholds, each followed by a
least-squares re-solve, and no ``|I| x |I|`` matrix is made.

Injective rounding (:func:`round_injective`) of a seamless map with no inverted tet moves
batches of integers by the foldover-free solve; where the least-squares re-solve of a batch keeps
every tet positive it is taken without the barrier's Newton steps.

Stiffening: tets whose parametric volume is not positive get their weight multiplied by
``stiffening_factor`` and the continuous unknowns are solved again (integers kept), up to
``stiffening_iters`` times.

Snapping (HexEx's sanitization; :func:`snap`): the continuous free unknowns are rounded to
multiples of ``2**-grid_bits`` and the integer ones are exact integers; every corner parameter is
a short sum of them with coefficients ``±1`` (or ``±1/2``, ``±2`` at half turns), so the corner
parameters are dyadic rationals computed exactly in float64, and the transitions
``u_t1 = R_f u_t0 + s_f`` hold *exactly* on every face: the validity check and the extraction
decide topology with exact arithmetic.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .solver import factorize

__all__ = ["round_greedy", "round_injective", "stiffen", "snap", "GRID_BITS", "solve_fixed", "param_volumes"]

GRID_BITS = 20
"""Parameters are snapped to multiples of ``2**-GRID_BITS`` (parameter magnitudes must stay below
``2**30`` so that every sum of a few of them is exact in float64)."""

_RHS_BATCH = 256


def param_volumes(uvw: np.ndarray) -> np.ndarray:
    """``6 x`` signed parametric volume of each tet, ``uvw (T, 4, 3)`` -> ``(T,)`` (float)."""
    d = uvw[:, 1:] - uvw[:, :1]
    return np.einsum("ti,ti->t", d[:, 0], np.cross(d[:, 1], d[:, 2]))


def round_greedy(A: sp.csr_matrix, b: np.ndarray, int_mask: np.ndarray, *, batch_error: float = 0.5,
                 backend: str = "auto", progress=None, flips=None, flip_budget: int = 40_000_000,
                 dense_budget: int = 2**26, thresholds=(0.1, 0.2, 0.3, 0.4, 0.5)) -> tuple[np.ndarray, dict]:
    """Greedy multiple rounding of the integer unknowns of ``min y^T A y - 2 b^T y`` (module docstring).

    Args:
        A: ``(m, m)`` SPD sparse matrix; ``b (m,)``.
        int_mask: ``(m,)`` bool, the integer unknowns.
        batch_error: the largest summed rounding distance of one step.
        backend: the :class:`~.solver.SPDFactor` backend.
        progress: an optional callable ``progress(n_fixed, n_total)``.
        flips: an optional callable ``flips(y) -> int`` (the map's tets that are not positively
            oriented for the unknowns ``y``). With it, and when ``m * |I| <= flip_budget``, the
            rounding is *flip-aware*: one integer at a time (the closest to an integer first), both
            neighbouring integers are tried and the one whose conditional optimum has fewer
            flipped tets is kept (then the nearer one). The conditional optimum of every unknown
            is kept up to date by rank-one updates of the ``(m, |I|)`` conditional covariance
            columns, from the same single factorization.
        dense_budget: the largest ``|I|^2`` (entries of the dense conditional covariance) for the
            one-factorization greedy rounding; above it (large meshes: ``|I| > 8192`` by default,
            512 MB) the rounding goes in blocks instead (:func:`_round_blocks`: the integers within
            ``thresholds[k]`` of an integer rounded together, each block followed by a
            least-squares re-solve with a fresh factorization), so no ``|I| x |I|`` matrix is made.

    Returns:
        ``(y (m,), info)``: ``y`` with every integer unknown an exact integer and the continuous
        ones optimal for them; ``info``: ``steps``, ``n_integers``, ``max_rounding`` (the largest
        distance moved by a rounding), ``undetermined`` (integers the others already fixed to a
        non-integer value), ``backend``, ``continuous_energy_y`` (the unrounded optimum).
    """
    m = A.shape[0]
    I = np.nonzero(int_mask)[0]
    fac = factorize(A, backend)
    y0 = fac.solve(b)
    info = {"steps": 0, "n_integers": int(I.size), "max_rounding": 0.0, "undetermined": 0, "backend": fac.backend}
    if I.size == 0:
        return y0, info
    if flips is not None and m * I.size <= flip_budget:
        return _round_flip_aware(fac, y0, I, flips, info, progress)
    if I.size * I.size > dense_budget:
        return _round_blocks(A, b, int_mask, y0, info, thresholds, backend, progress)
    # C = (A^{-1})_{II}, from |I| solves in batches
    C = np.empty((I.size, I.size))
    for s in range(0, I.size, _RHS_BATCH):
        cols = I[s:s + _RHS_BATCH]
        E = np.zeros((m, cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        C[:, s:s + cols.size] = fac.solve(E)[I]
    C = 0.5 * (C + C.T)
    x = y0[I].copy()
    scale = max(float(np.abs(np.diag(C)).max()), 1e-300)
    tiny = 1e-12 * scale
    rem = np.arange(I.size)
    undetermined = 0
    max_round = 0.0
    while rem.size:
        var = np.diag(C)[rem]
        det = var <= tiny  # already determined by the fixed ones
        if det.any():
            idx = rem[det]
            frac = np.abs(x[idx] - np.round(x[idx]))
            undetermined += int((frac > 1e-9).sum())
            x[idx] = np.where(frac <= 1e-9, np.round(x[idx]), x[idx])
            rem = rem[~det]
            if not rem.size:
                break
        d = np.abs(x[rem] - np.round(x[rem]))
        order = np.argsort(d, kind="stable")
        cum = np.cumsum(d[order])
        k = max(1, int(np.searchsorted(cum, batch_error, side="right")))
        Bi = rem[order[:k]]
        nB = np.round(x[Bi])
        max_round = max(max_round, float(np.abs(nB - x[Bi]).max()))
        # condition on x_B = n_B (only the remaining rows matter)
        rest = np.setdiff1d(rem, Bi, assume_unique=True)
        CBB = C[np.ix_(Bi, Bi)]
        try:
            L = np.linalg.cholesky(CBB)
            solveB = lambda r: np.linalg.solve(L.T, np.linalg.solve(L, r))  # noqa: E731
        except np.linalg.LinAlgError:
            pinv = np.linalg.pinv(CBB)
            solveB = lambda r: pinv @ r  # noqa: E731
        if rest.size:
            CrB = C[np.ix_(rest, Bi)]
            x[rest] += CrB @ solveB(nB - x[Bi])
            C[np.ix_(rest, rest)] -= CrB @ solveB(CrB.T)
        x[Bi] = nB
        rem = rest
        info["steps"] += 1
        if progress is not None:
            progress(I.size - rem.size, I.size)
    info["max_rounding"] = max_round
    info["undetermined"] = undetermined
    y = solve_fixed(A, b, int_mask, x, backend=backend)
    return y, info


def _round_blocks(A, b, int_mask, y0, info, thresholds, backend, progress):
    """Rounding in blocks: for each threshold, the unfixed integers within it of an integer (at
    least the closest one) are rounded together, then every unfixed unknown re-solved by least
    squares with the rounded ones fixed (:func:`solve_fixed`); the rest at the last threshold."""
    I = np.nonzero(int_mask)[0]
    y = y0.copy()
    fixed = np.zeros(y.size, bool)
    max_round = 0.0
    steps = 0
    for k, th in enumerate(thresholds):
        rem = I[~fixed[I]]
        if not rem.size:
            break
        d = np.abs(y[rem] - np.round(y[rem]))
        last = k == len(thresholds) - 1
        sel = rem if last else (rem[d <= th] if (d <= th).any() else rem[np.argsort(d, kind="stable")[:1]])
        max_round = max(max_round, float(np.abs(y[sel] - np.round(y[sel])).max()))
        y[sel] = np.round(y[sel])
        fixed[sel] = True
        y = solve_fixed(A, b, fixed, y[fixed], backend=backend)
        steps += 1
        if progress is not None:
            progress(int(fixed[I].sum()), I.size)
    info.update(steps=steps, max_rounding=max_round, blocks=True)
    return y, info


def _round_flip_aware(fac, y0, I, flips, info, progress):
    """One integer at a time, each rounding chosen among its two neighbours by the flips it makes."""
    m = y0.size
    K = np.empty((m, I.size))  # conditional covariance columns Cov(y, y_I)
    for s in range(0, I.size, _RHS_BATCH):
        cols = I[s:s + _RHS_BATCH]
        E = np.zeros((m, cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        K[:, s:s + cols.size] = fac.solve(E)
    y = y0.copy()
    rem = np.ones(I.size, bool)
    scale = max(float(np.abs(K[I, np.arange(I.size)]).max()), 1e-300)
    undetermined, max_round, changed = 0, 0.0, 0
    for step in range(I.size):
        r = np.nonzero(rem)[0]
        xi = y[I[r]]
        d = np.abs(xi - np.round(xi))
        j = int(r[np.argmin(d)])
        v = K[I[j], j]
        x = y[I[j]]
        if v <= 1e-12 * scale:  # already determined by the fixed ones
            if abs(x - round(x)) > 1e-9:
                undetermined += 1
            else:
                y[I[j]] = round(x)
            rem[j] = False
            continue
        near = float(np.round(x))
        other = near + (1.0 if x > near else -1.0)
        best = None
        for cand in (near, other):
            yc = y + ((cand - x) / v) * K[:, j]
            nf = int(flips(yc))
            key = (nf, abs(cand - x))
            if best is None or key < best[0]:
                best = (key, cand, yc)
            if nf == 0:
                break
        (_, dist), cand, yc = best
        changed += cand != near
        max_round = max(max_round, dist)
        y = yc
        y[I[j]] = cand
        # condition the covariance on y_I[j] = cand
        kj = K[:, j].copy()
        K -= np.outer(kj, K[I[j], :] / v)
        rem[j] = False
        if progress is not None:
            progress(int((~rem).sum()), I.size)
    info.update(steps=I.size, max_rounding=max_round, undetermined=undetermined, flip_aware=True,
                rounded_away=int(changed))
    return y, info


def solve_fixed(A: sp.csr_matrix, b: np.ndarray, int_mask: np.ndarray, int_values: np.ndarray, *,
                backend: str = "auto") -> np.ndarray:
    """The optimum of ``y^T A y - 2 b^T y`` with ``y[int_mask] = int_values`` (one factorization of
    the continuous block)."""
    A = sp.csr_matrix(A)
    Cn = np.nonzero(~int_mask)[0]
    I = np.nonzero(int_mask)[0]
    y = np.empty(A.shape[0])
    y[I] = int_values
    if Cn.size:
        Acc = A[Cn][:, Cn]
        rhs = b[Cn] - A[Cn][:, I] @ y[I]
        y[Cn] = factorize(Acc, backend).solve(rhs)
    return y


def round_injective(jac, y: np.ndarray, int_mask: np.ndarray, *, thresholds=(0.1, 0.2, 0.3, 0.4, 0.5),
                    ignore: np.ndarray | None = None, w_fit: float = 1.0, w_sd: float = 1.0, backend: str = "auto",
                    progress=None, lsq: tuple | None = None) -> tuple[np.ndarray, dict]:
    """Round the integer unknowns of a map with no inverted tet, keeping it so.

    The integers are rounded in batches: those within ``thresholds[k]`` of an integer (at least
    the closest one), all at once; each batch is moved to its integers by the injective solve
    (:func:`~.injective.move_fixed`: the other unknowns follow, the line search never crosses a
    zero determinant, the integers rounded before are held). A batch that cannot move without a
    fold is halved; an integer that cannot move alone to its nearest integer tries the other
    neighbour; one that can do neither waits until the others are rounded and is tried again
    once (the others' moves change what it meets). After each threshold the distances are
    recomputed from the current map.

    With ``lsq = (A, b)`` (the least-squares energy ``y^T A y - 2 b^T y`` of the same unknowns,
    given when its optimum is the seamless map, i.e. that map did not fold): every integer is
    first rounded at once, and each batch before its injective move, by the plain least-squares
    re-solve with the batch and the integers rounded before fixed (one factorization); when every
    determinant of that map stays above the moves' floor (``1e-9``) it is taken without the
    barrier's Newton steps. The guarantee is the same (no accepted map has a tet at or below the
    floor); the map reached may differ (least squares instead of the barrier's optimum between the
    integers). Counted in ``info["lsq_accepted"]``.

    Args:
        jac: the :class:`~.injective.TetJacobians` of the seamless problem.
        y: ``(m,)`` the free unknowns of a map with every ``det J > 0`` (but the ``ignore (k,)``
            tets: flat whatever the unknowns, :func:`~.injective.minimize_barrier`).
        int_mask: ``(m,)`` bool, the integer unknowns.
        thresholds: the distance thresholds of the batches.
        w_fit, w_sd, backend: of the injective solve.
        progress: optional ``progress(n_rounded, n_total)``.
        lsq: optional ``(A, b)``, see above.

    Returns:
        ``(y, info)``: ``y`` with every integer it could round an exact integer and no tet
        inverted; ``info``: ``n_integers``, ``rounded``, ``failed`` (free indices of the integers
        left unrounded: the map is then not an integer-grid map), ``rounded_away`` (to the farther
        neighbour), ``moves`` (injective solves), ``max_rounding``, ``lsq_tries`` /
        ``lsq_accepted`` (least-squares re-solves tried / taken).
    """
    from .injective import move_fixed

    y = np.array(y, np.float64, copy=True)
    I = np.nonzero(int_mask)[0]
    done = np.zeros(y.size, bool)
    info = {"n_integers": int(I.size), "rounded": 0, "failed": [], "rounded_away": 0, "moves": 0, "max_rounding": 0.0,
            "lsq_tries": 0, "lsq_accepted": 0}
    kw = dict(w_fit=w_fit, w_sd=w_sd, backend=backend, ignore=ignore)
    opened = None if ignore is None else np.setdiff1d(np.arange(jac.n_tets), ignore)

    def accept(idx, tgt, y_new):
        nonlocal y
        y = y_new
        done[idx] = True
        info["rounded"] += idx.size
        info["max_rounding"] = max(info["max_rounding"], float(np.abs(tgt - y0_of[idx]).max()))
        if progress is not None:
            progress(info["rounded"], I.size)

    def try_lsq(idx, tgt):
        if lsq is None:
            return False
        from .injective import _DET_MOVE_MIN

        info["lsq_tries"] += 1
        fixed = done.copy()
        fixed[idx] = True
        vals = y.copy()
        vals[idx] = tgt
        y_new = solve_fixed(lsq[0], lsq[1], fixed, vals[fixed], backend=backend)
        det = np.linalg.det(jac(y_new))
        if (det if opened is None else det[opened]).min(initial=np.inf) <= _DET_MOVE_MIN:
            return False
        info["lsq_accepted"] += 1
        accept(idx, tgt, y_new)
        return True

    def try_move(idx, tgt):
        info["moves"] += 1
        y_new, ok, _ = move_fixed(jac, y, idx, tgt, held=done, **kw)
        if ok:
            accept(idx, tgt, y_new)
        return ok

    def round_batch(idx):
        """Round ``idx`` to their nearest integers, halving on failure; returns the ones left."""
        tgt = np.round(y[idx])
        if try_lsq(idx, tgt) or try_move(idx, tgt):
            return np.zeros(0, np.int64)
        if idx.size > 1:
            h = idx.size // 2
            left = round_batch(idx[:h])
            return np.concatenate([left, round_batch(idx[h:])])
        i = idx[:1]
        near = float(tgt[0])
        other = near + (1.0 if y[i[0]] > near else -1.0)
        if try_move(i, np.array([other])):
            info["rounded_away"] += 1
            return np.zeros(0, np.int64)
        return i

    y0_of = y.copy()
    if I.size:
        try_lsq(I, np.round(y[I]))  # everything at once, when the least-squares map stays valid
    for th in thresholds:
        rem = I[~done[I]]
        if not rem.size:
            break
        d = np.abs(y[rem] - np.round(y[rem]))
        sel = rem[d <= th] if (d <= th).any() else rem[np.argsort(d)[:1]]
        sel = sel[np.argsort(np.abs(y[sel] - np.round(y[sel])), kind="stable")]
        round_batch(sel)  # what fails here is tried again below, after the others
    rem = I[~done[I]]
    left = round_batch(rem) if rem.size else np.zeros(0, np.int64)
    info["failed"] = [int(i) for i in left]
    return y, info


def stiffen(prob, y: np.ndarray, int_mask: np.ndarray, *, iters: int = 10, factor: float = 4.0,
            backend: str = "auto") -> tuple[np.ndarray, int]:
    """Stiffening: multiply the fitting weight of the tets that are not positively oriented by
    ``factor`` and solve the continuous unknowns again (integers kept), up to ``iters`` times.

    Returns ``(y, iterations run)``.
    """
    weights = np.ones(prob.vol.size)
    uvw = prob.corner_params(y)
    done = 0
    for _ in range(iters):
        flip = param_volumes(uvw) <= 0
        if not flip.any():
            break
        weights[flip] *= factor
        Aw, bw, _ = prob.energy_matrices(weights)
        y = solve_fixed(Aw, bw, int_mask, y[int_mask], backend=backend)
        uvw = prob.corner_params(y)
        done += 1
    return y, done


def snap(prob, y: np.ndarray, int_mask: np.ndarray | None, grid_bits: int, edge_length: float):
    """Snapping to the dyadic grid (module docstring): the free unknowns ``y (n,)`` rounded to
    multiples of ``2**-grid_bits``, those of ``int_mask (n,) bool`` to integers (``None``: none).

    Returns ``(y_snapped (n,), uvw (T, 4, 3))``, the corner parameters ``prob.corner_params`` of
    the snapped unknowns (exact dyadic rationals).

    Raises:
        ValueError: a corner parameter reaches ``2**30`` (the sums stop being exact in float64):
            ``edge_length`` is too small for the mesh.
    """
    scale = float(2 ** grid_bits)
    ys = np.round(y * scale) / scale
    if int_mask is not None:
        ys[int_mask] = np.round(y[int_mask])
    uvw = prob.corner_params(ys)
    if np.abs(uvw).max(initial=0.0) >= 2.0 ** 30:
        raise ValueError(f"the parameters reach {np.abs(uvw).max():.3g} >= 2**30: edge_length {edge_length:g} is too "
                         f"small for this mesh")
    return ys, uvw
