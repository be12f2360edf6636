"""The generic (torch) kernels of ``torchconn::tet_dd``: the tet closed form, component-major.

Plain functions on plain tensors (they run inside the custom op, below autograd) in torch
operations only, so they run on every device and dtype. :func:`forward` is also the formula
that the op's double backward differentiates with autograd (every step is out of place).

Layout: the connection is ``(N, E, 3, 3)`` (leading batch flattened to ``N``), the solder form
``(N, E, 2, 3)``. The edge tables are laid out component-major as ``(N, 18 E)`` (``R`` then
``Rᵀ`` components) and ``(N, 6 E)`` (``θ̃_ij`` then ``θ̃_ji``); the per-tet data is gathered with
9 + 3 ``index_select`` of ``(6T,)`` / ``(7T,)`` and the backward scatters with ``index_add_``.
Every ``(N, T)`` component is contiguous in ``T``, so a 3x3 matrix-vector product is 9
multiply-adds on contiguous memory (several times faster on CPU than batched 3x3 ``bmm``).
"""
from __future__ import annotations

import torch

__all__ = ["forward", "backward", "tet_dd_dense"]


def tet_dd_dense(rot: torch.Tensor, theta: torch.Tensor):
    """The regrouped formula with batched ``bmm`` on per-tet data (``(T, 6, 3, 3)``, ``(T, 7, 3)``);
    returns the output ``(T, 3)`` and the stacked intermediates ``(y_c, y_d)``, ``(x_b, x_c, x_d)``."""
    Rbc, Rbd, Rcd = rot[:, 3], rot[:, 4], rot[:, 5]
    t_ba, t_ca, t_da, t_cb, t_db, t_dc, t_cd = theta.unbind(1)
    # round 1 (R_yx = R_xyᵀ: transposed products, no copies)
    p_cd = Rcd.unsqueeze(1) @ torch.stack((t_db, t_da), 1).unsqueeze(-1)  # R_cd θ̃_db, R_cd θ̃_da
    p_dc = Rcd.transpose(-1, -2).unsqueeze(1) @ torch.stack((t_cb, t_ca), 1).unsqueeze(-1)  # R_dc θ̃_cb, R_dc θ̃_ca
    p_ba = torch.stack((Rbc, Rbd), 1).transpose(-1, -2) @ t_ba[:, None, :, None]  # R_cb θ̃_ba, R_db θ̃_ba
    p_cd, p_dc, p_ba = p_cd.squeeze(-1), p_dc.squeeze(-1), p_ba.squeeze(-1)
    sixth = 1.0 / 6.0
    y_c = (p_cd[:, 0] - t_ca) * sixth - t_cb / 3.0 + 0.5 * t_cd
    y_d = (t_da - p_dc[:, 0]) * sixth + t_db / 3.0 - 0.5 * t_dc
    x_c = (p_ba[:, 0] - p_cd[:, 1]) * sixth + 0.5 * (t_cb - t_cd)
    x_d = (p_dc[:, 1] - p_ba[:, 1]) * sixth - 0.5 * (t_db - t_dc)
    # round 2: X_b = R_bc y_c + R_bd y_d
    y = torch.stack((y_c, y_d), 1)
    x_b = (rot[:, 3:5] @ y.unsqueeze(-1)).squeeze(-1).sum(1)
    # round 3: R_ab X_b + R_ac X_c + R_ad X_d
    x = torch.stack((x_b, x_c, x_d), 1)
    out = (rot[:, 0:3] @ x.unsqueeze(-1)).squeeze(-1).sum(1)
    return out, y, x


# ----------------------------------------------------------------------------- component algebra

def _mv(M, v):
    """``M v`` on unbound components: ``M`` 9 tensors (row-major), ``v`` 3 tensors -> 3 tensors."""
    return tuple(torch.addcmul(torch.addcmul(M[3 * i] * v[0], M[3 * i + 1], v[1]), M[3 * i + 2], v[2])
                 for i in range(3))


def _mtv(M, v):
    """``Mᵀ v`` on unbound components."""
    return tuple(torch.addcmul(torch.addcmul(M[i] * v[0], M[3 + i], v[1]), M[6 + i], v[2]) for i in range(3))


def _mv2(M, v, N, w):
    """``M v + N w`` on unbound components."""
    out = []
    for i in range(3):
        acc = M[3 * i] * v[0]
        for j in (1, 2):
            acc = torch.addcmul(acc, M[3 * i + j], v[j])
        for j in range(3):
            acc = torch.addcmul(acc, N[3 * i + j], w[j])
        out.append(acc)
    return tuple(out)


def _lin(*terms):
    """``Σ c_k v_k`` for ``(c_k, v_k)`` pairs, each ``v_k`` 3 tensors (``torch.add(.., alpha=)``)."""
    c0, v0 = terms[0]
    out = [v0[i] * c0 if c0 != 1.0 else v0[i] for i in range(3)]
    for c, v in terms[1:]:
        out = [torch.add(out[i], v[i], alpha=c) for i in range(3)]
    return tuple(out)


def _add3(a, b):
    return tuple(a[i] + b[i] for i in range(3))


def _soa_forward(R, t):
    """The closed form on components; ``R`` 6 x 9 and ``t`` 7 x 3 tensors. Out of place throughout
    (differentiable). Returns ``out`` (3 tensors) and the intermediates ``y_c, y_d, x_b, x_c, x_d``."""
    Rab, Rac, Rad, Rbc, Rbd, Rcd = R
    t_ba, t_ca, t_da, t_cb, t_db, t_dc, t_cd = t
    s6 = 1.0 / 6.0
    p_cd0, p_cd1 = _mv(Rcd, t_db), _mv(Rcd, t_da)
    p_dc0, p_dc1 = _mtv(Rcd, t_cb), _mtv(Rcd, t_ca)
    p_cb, p_db = _mtv(Rbc, t_ba), _mtv(Rbd, t_ba)
    y_c = _lin((s6, p_cd0), (-s6, t_ca), (-1.0 / 3.0, t_cb), (0.5, t_cd))
    y_d = _lin((s6, t_da), (-s6, p_dc0), (1.0 / 3.0, t_db), (-0.5, t_dc))
    x_c = _lin((s6, p_cb), (-s6, p_cd1), (0.5, t_cb), (-0.5, t_cd))
    x_d = _lin((s6, p_dc1), (-s6, p_db), (-0.5, t_db), (0.5, t_dc))
    x_b = _mv2(Rbc, y_c, Rbd, y_d)
    out = _add3(_mv2(Rab, x_b, Rac, x_c), _mv(Rad, x_d))
    return out, (y_c, y_d, x_b, x_c, x_d)


def _outer_into(G, a, b, acc: bool):
    """``G += a bᵀ`` (or ``G = a bᵀ``) into the 9 component views ``G`` (in place)."""
    for i in range(3):
        for j in range(3):
            if acc:
                G[3 * i + j].addcmul_(a[i], b[j])
            else:
                torch.mul(a[i], b[j], out=G[3 * i + j])


def _soa_backward(R, t, inter, g, gR):
    """Reverse of :func:`_soa_forward`: writes every ``∂L/∂R_p`` into the 9 component views
    ``gR[p]`` and returns ``∂L/∂θ̃`` (7 x 3 tensors)."""
    Rab, Rac, Rad, Rbc, Rbd, Rcd = R
    t_ba, t_ca, t_da, t_cb, t_db, t_dc, t_cd = t
    y_c, y_d, x_b, x_c, x_d = inter
    s6 = 1.0 / 6.0
    _outer_into(gR[0], g, x_b, False)
    _outer_into(gR[1], g, x_c, False)
    _outer_into(gR[2], g, x_d, False)
    gx_b, gx_c, gx_d = _mtv(Rab, g), _mtv(Rac, g), _mtv(Rad, g)
    _outer_into(gR[3], gx_b, y_c, False)
    _outer_into(gR[4], gx_b, y_d, False)
    gy_c, gy_d = _mtv(Rbc, gx_b), _mtv(Rbd, gx_b)
    gp_cd0, gp_dc0 = _lin((s6, gy_c)), _lin((-s6, gy_d))
    gp_cb, gp_cd1 = _lin((s6, gx_c)), _lin((-s6, gx_c))
    gp_dc1, gp_db = _lin((s6, gx_d)), _lin((-s6, gx_d))
    _outer_into(gR[5], gp_cd0, t_db, False)
    _outer_into(gR[5], gp_cd1, t_da, True)
    _outer_into(gR[5], t_cb, gp_dc0, True)
    _outer_into(gR[5], t_ca, gp_dc1, True)
    _outer_into(gR[3], t_ba, gp_cb, True)
    _outer_into(gR[4], t_ba, gp_db, True)
    return (
        _mv2(Rbc, gp_cb, Rbd, gp_db),                                    # θ̃_ba
        _lin((1.0, _mv(Rcd, gp_dc1)), (-s6, gy_c)),                      # θ̃_ca
        _lin((1.0, _mtv(Rcd, gp_cd1)), (s6, gy_d)),                      # θ̃_da
        _lin((1.0, _mv(Rcd, gp_dc0)), (-1.0 / 3.0, gy_c), (0.5, gx_c)),  # θ̃_cb
        _lin((1.0, _mtv(Rcd, gp_cd0)), (1.0 / 3.0, gy_d), (-0.5, gx_d)),  # θ̃_db
        _lin((-0.5, gy_d), (0.5, gx_d)),                                 # θ̃_dc
        _lin((0.5, gy_c), (-0.5, gx_c)),                                 # θ̃_cd
    )


# ----------------------------------------------------------------------------- gathers

def _bases(rot_index: torch.Tensor, theta_index: torch.Tensor, E: int):
    """Flat component-major bases ``(6 T,)``, ``(7 T,)`` (pair-major): column ``e`` plus ``9E``
    (``3E``) for the reversed direction."""
    rb = (rot_index % 2 * (9 * E) + rot_index // 2).t().reshape(-1)
    tb = (theta_index % 2 * (3 * E) + theta_index // 2).t().reshape(-1)
    return rb, tb


def _gather(table: torch.Tensor, base: torch.Tensor, comps: int, E: int, P: int) -> torch.Tensor:
    """``out[q, n, p, t] = table[n, q E + base[p T + t]]``: ``(comps, N, P, T)``."""
    N = table.shape[0]
    return torch.stack([table.index_select(1, base + q * E) for q in range(comps)], 0).reshape(comps, N, P, -1)


def _tables(edge_rot, edge_theta, rot_index, theta_index):
    """Per-tet component arrays ``rot (9, N, 6, T)`` and ``th (3, N, 7, T)`` (differentiable)."""
    N, E = edge_rot.shape[0], edge_rot.shape[1]
    rb, tb = _bases(rot_index, theta_index, E)
    flat = edge_rot.reshape(N, E, 9)
    table = torch.cat((flat.transpose(1, 2), edge_rot.transpose(-1, -2).reshape(N, E, 9).transpose(1, 2)), 1)
    rot = _gather(table.reshape(N, 18 * E), rb, 9, E, 6)
    tt = edge_theta.permute(0, 2, 3, 1).reshape(N, 6 * E)  # (N, 2, 3, E): θ̃_ij rows then θ̃_ji rows
    return rot, _gather(tt, tb, 3, E, 7), (rb, tb)


def _unbind(rot, th):
    """``R`` 6 x 9 and ``t`` 7 x 3 component tensors ``(N, T)`` (views)."""
    # unbind (backward: one stack) rather than 54 + 21 selects (backward: a zero-filled full-size
    # tensor each), which matters when the forward is differentiated (double backward)
    rq = [r.unbind(1) for r in rot.unbind(0)]  # rq[q][p]: (N, T)
    tc = [t.unbind(1) for t in th.unbind(0)]
    return [[rq[q][p] for q in range(9)] for p in range(6)], [[tc[c][k] for c in range(3)] for k in range(7)]


def forward(edge_rot: torch.Tensor, edge_theta: torch.Tensor, rot_index: torch.Tensor,
            theta_index: torch.Tensor) -> torch.Tensor:
    """``(N, E, 3, 3)``, ``(N, E, 2, 3)`` -> ``(N, T, 3)`` (differentiable by autograd)."""
    rot, th, _ = _tables(edge_rot, edge_theta, rot_index, theta_index)
    out, _ = _soa_forward(*_unbind(rot, th))
    return torch.stack(out, -1)


def backward(edge_rot: torch.Tensor, edge_theta: torch.Tensor, grad: torch.Tensor, rot_index: torch.Tensor,
             theta_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Vector-Jacobian product of :func:`forward`: ``grad (N, T, 3)`` -> ``(N, E, 3, 3)``, ``(N, E, 2, 3)``.

    Hand-written (not recorded): in-place writes into preallocated component buffers, then one
    ``index_add_`` per component."""
    N, E = edge_rot.shape[0], edge_rot.shape[1]
    rot, th, (rb, tb) = _tables(edge_rot, edge_theta, rot_index, theta_index)
    R, t = _unbind(rot, th)
    _, inter = _soa_forward(R, t)
    gc = tuple(grad[..., i].contiguous() for i in range(3))
    g_rot = torch.empty_like(rot)
    g_th = torch.empty_like(th)
    vals = _soa_backward(R, t, inter, gc, [[g_rot[q, :, p] for q in range(9)] for p in range(6)])
    for k in range(7):
        for c in range(3):
            g_th[c, :, k].copy_(vals[k][c])
    gtab = edge_rot.new_zeros(N, 18 * E)
    for q in range(9):
        gtab.index_add_(1, rb + q * E, g_rot[q].reshape(N, -1))
    gtab = gtab.reshape(N, 18, E)
    g_edge_rot = (gtab[:, :9].transpose(1, 2) + gtab[:, 9:].transpose(1, 2).reshape(N, E, 3, 3).transpose(-1, -2)
                  .reshape(N, E, 9)).reshape(N, E, 3, 3)
    gtt = edge_rot.new_zeros(N, 6 * E)
    for c in range(3):
        gtt.index_add_(1, tb + c * E, g_th[c].reshape(N, -1))
    return g_edge_rot, gtt.reshape(N, 2, 3, E).permute(0, 3, 1, 2).contiguous()
