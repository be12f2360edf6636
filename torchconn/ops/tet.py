"""Averaged ``d∇d∇θ`` on tets as an op: the per-tet closed form of ``𝔡∇ Alt 𝔡∇ Alt θ̃``.

The end-of-Ch. 5 tetrahedron formula (:func:`torchconn.dec.dnabla.wedge_curvature_solder_tet`)
regrouped as three rounds of batched matrix-vector products on the 6 edge rotations of each
tet, with ``θ̃`` formed once per *edge* (both directions), never per tet, evaluated
component-major with a hand-written backward (itself differentiable: double backward,
``create_graph`` and Hessian-vector products are exact) on gather tables built once per mesh
(:class:`TetKernel`, cached with ``mesh.require``). Any float dtype and device; constants
follow the input. :func:`tet_dd_solder` is the op that
:func:`torchconn.dec.dnabla.averaged_dd_solder` and :func:`torchconn.dec.dnabla.wedge_solder`
call; it returns ``None`` where the kernel does not apply (rank other than 3), and the caller
then evaluates its generic operators.
"""
from __future__ import annotations

import torch

from ._cache import require as _require
from ._mat import _matTvec, _matvec
from .so3 import sqrt as _sqrt

__all__ = ["TetKernel", "tet_kernel", "edge_solder_sqrt", "tet_dd_from_rotations", "tet_dd_solder"]

_FIELDS = ("rot_index", "theta_index", "rot_base", "theta_base")


class TetKernel:
    """Gather tables of a :class:`~torchconn.mesh.TetMesh` for the fused tet kernels (built once).

    Attributes (long, on the mesh device):
        rot_index ``(T, 6)``: index into ``torch.stack((R, Rᵀ), 1).reshape(2E, 3, 3)`` giving the
            oriented ``R_{x_i x_j}`` of local pair ``p`` (``pair_list(4)`` order), i.e.
            ``2 e + (sign < 0)``.
        theta_index ``(T, 7)``: index into ``stack((θ̃_ij, θ̃_ji), 1).reshape(2E, 3)`` of the
            seven directed edges the formula reads, ``ba, ca, da, cb, db, dc, cd`` (local labels
            ``a, b, c, d = 0..3``).
        rot_base ``(6, T)``, theta_base ``(7, T)``: the same in component-major layout
            (:func:`_soa_gather`): column ``e`` plus ``9E`` (``3E``) for the reversed direction.
    """

    # local pairs 01 02 03 12 13 23 and the directed edges (x, y) read as θ̃_xy
    _DIRECTED = ((1, 0), (2, 0), (3, 0), (2, 1), (3, 1), (3, 2), (2, 3))

    def __init__(self, mesh):
        te = mesh.tet_edges
        neg = (mesh.tet_edge_signs < 0).long()
        self.rot_index = 2 * te + neg
        pair = {(0, 1): 0, (0, 2): 1, (0, 3): 2, (1, 2): 3, (1, 3): 4, (2, 3): 5}
        cols = []
        for x, y in self._DIRECTED:
            p = pair[(min(x, y), max(x, y))]
            # the tet traverses local pair p as stored when sign > 0; directed (x, y) with x > y
            # runs against the local order, so against the stored edge iff sign > 0
            against = neg[:, p] if x < y else 1 - neg[:, p]
            cols.append(2 * te[:, p] + against)
        self.theta_index = torch.stack(cols, 1)
        E = int(mesh.edges.shape[0])
        # component-major ("structure of arrays") bases, pair-major (6, T) / (7, T): component
        # q of the oriented R_p is row q (+ 9 if reversed) of the (18, E) table [Rᵀ-rows; R-rows]
        self.rot_base = (self.rot_index % 2 * 9 * E + self.rot_index // 2).t().contiguous()
        self.theta_base = (self.theta_index % 2 * 3 * E + self.theta_index // 2).t().contiguous()
        self.n_edges = E

    def to(self, device) -> "TetKernel":
        """A copy with the tables on ``device`` (``self`` is left as it is)."""
        new = object.__new__(TetKernel)
        for name in _FIELDS:
            setattr(new, name, getattr(self, name).to(device))
        new.n_edges = self.n_edges
        return new


def tet_kernel(mesh, device: torch.device | str | None = None) -> TetKernel:
    """The :class:`TetKernel` of ``mesh`` on ``device`` (default: the mesh's), cached with ``mesh.require``."""
    k = _require(mesh, "ops.tet_kernel", TetKernel)
    if device is None or k.rot_index.device == torch.device(device):
        return k
    dev = torch.device(device)
    return _require(mesh, f"ops.tet_kernel.{dev}", lambda m: k.to(dev))


def edge_solder_sqrt(half_rot: torch.Tensor, edge_vec: torch.Tensor) -> torch.Tensor:
    """Half-transported solder form of both directions of every edge: ``(E, 2, 3)``.

    ``[e, 0] = θ̃_ij = √R_ij (v_j - v_i)`` and ``[e, 1] = θ̃_ji = √R_ji (v_i - v_j) =
    -√R_ijᵀ (v_j - v_i)`` for ``edges[e] = (i, j)`` (report Sec. 3.3, docs/conventions.md §1).

    Args:
        half_rot: ``(E, 3, 3)`` ``√R_ij``; edge_vec: ``(E, 3)`` ``v_j - v_i``.
    """
    return torch.stack((_matvec(half_rot, edge_vec), -_matTvec(half_rot, edge_vec)), 1)


def _tet_dd_forward(rot: torch.Tensor, theta: torch.Tensor):
    """The regrouped formula of :func:`tet_dd_from_rotations` with batched ``bmm``; returns the
    output and the stacked intermediates ``(y_c, y_d)``, ``(x_b, x_c, x_d)``."""
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


def _outer_into(G, a, b, acc: bool):
    """``G += a bᵀ`` (or ``G = a bᵀ``) into the 9 component views ``G`` (in place)."""
    for i in range(3):
        for j in range(3):
            if acc:
                G[3 * i + j].addcmul_(a[i], b[j])
            else:
                torch.mul(a[i], b[j], out=G[3 * i + j])


class _OuterInPlace:
    """Sink of :func:`_soa_backward`: ``∂L/∂R_p`` written into preallocated component views.

    The first-order backward (no graph recorded): no temporaries, no final stack."""

    def __init__(self, gR):
        self.gR = gR

    def __call__(self, p: int, a, b, acc: bool) -> None:
        _outer_into(self.gR[p], a, b, acc)


class _OuterRecorded:
    """Sink of :func:`_soa_backward`: ``∂L/∂R_p`` built out of place (``mul``, ``addcmul``).

    For a recorded backward (``create_graph``): ``out=`` and in-place writes into a buffer
    that autograd does not track are not differentiable. ``gR[p]`` is 9 tensors ``(T,)``."""

    def __init__(self):
        self.gR = [None] * 6

    def __call__(self, p: int, a, b, acc: bool) -> None:
        if acc:
            self.gR[p] = tuple(torch.addcmul(self.gR[p][3 * i + j], a[i], b[j]) for i in range(3) for j in range(3))
        else:
            self.gR[p] = tuple(a[i] * b[j] for i in range(3) for j in range(3))


def _soa_forward(R, t):
    """Component form of :func:`_tet_dd_forward`; ``R`` 6 x 9 and ``t`` 7 x 3 tensors ``(T,)``."""
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
    out = _mv2(Rab, x_b, Rac, x_c)
    out = _add3(out, _mv(Rad, x_d))
    return out, (y_c, y_d, x_b, x_c, x_d)


def _add3(a, b):
    return tuple(a[i] + b[i] for i in range(3))


def _soa_backward(R, t, inter, g, outer):
    """Reverse of :func:`_soa_forward`: returns ``∂L/∂θ̃`` (7 x 3 tensors) and hands every
    ``∂L/∂R_p`` term ``a bᵀ`` to ``outer(p, a, b, acc)`` (:class:`_OuterInPlace`,
    :class:`_OuterRecorded`). Differentiable when ``outer`` is (all other steps are out of place)."""
    Rab, Rac, Rad, Rbc, Rbd, Rcd = R
    t_ba, t_ca, t_da, t_cb, t_db, t_dc, t_cd = t
    y_c, y_d, x_b, x_c, x_d = inter
    s6 = 1.0 / 6.0
    outer(0, g, x_b, False)
    outer(1, g, x_c, False)
    outer(2, g, x_d, False)
    gx_b, gx_c, gx_d = _mtv(Rab, g), _mtv(Rac, g), _mtv(Rad, g)
    outer(3, gx_b, y_c, False)
    outer(4, gx_b, y_d, False)
    gy_c, gy_d = _mtv(Rbc, gx_b), _mtv(Rbd, gx_b)
    gp_cd0, gp_dc0 = _lin((s6, gy_c)), _lin((-s6, gy_d))
    gp_cb, gp_cd1 = _lin((s6, gx_c)), _lin((-s6, gx_c))
    gp_dc1, gp_db = _lin((s6, gx_d)), _lin((-s6, gx_d))
    outer(5, gp_cd0, t_db, False)
    outer(5, gp_cd1, t_da, True)
    outer(5, t_cb, gp_dc0, True)
    outer(5, t_ca, gp_dc1, True)
    outer(3, t_ba, gp_cb, True)
    outer(4, t_ba, gp_db, True)
    return (
        _mv2(Rbc, gp_cb, Rbd, gp_db),                                    # θ̃_ba
        _lin((1.0, _mv(Rcd, gp_dc1)), (-s6, gy_c)),                      # θ̃_ca
        _lin((1.0, _mtv(Rcd, gp_cd1)), (s6, gy_d)),                      # θ̃_da
        _lin((1.0, _mv(Rcd, gp_dc0)), (-1.0 / 3.0, gy_c), (0.5, gx_c)),  # θ̃_cb
        _lin((1.0, _mtv(Rcd, gp_cd0)), (1.0 / 3.0, gy_d), (-0.5, gx_d)),  # θ̃_db
        _lin((-0.5, gy_d), (0.5, gx_d)),                                 # θ̃_dc
        _lin((0.5, gy_c), (-0.5, gx_c)),                                 # θ̃_cd
    )


def _soa_gather(table: torch.Tensor, base: torch.Tensor, comps: int, E: int) -> torch.Tensor:
    """``out[q, p, t] = table[q * E + base[p, t]]``: ``(comps, P, T)`` from a flat component table."""
    flat_base = base.reshape(-1)
    return torch.stack([table[q * E:].index_select(0, flat_base) for q in range(comps)], 0).reshape(
        comps, *base.shape)


def _soa_scatter(vals: torch.Tensor, base: torch.Tensor, rows: int, E: int) -> torch.Tensor:
    """Adjoint of :func:`_soa_gather`: ``(rows * E,)`` sums of ``vals (comps, P, T)``."""
    out = vals.new_zeros(rows * E)
    flat_base = base.reshape(-1)
    for q in range(vals.shape[0]):
        out[q * E:].index_add_(0, flat_base, vals[q].reshape(-1))
    return out


def _soa_tables(edge_rot, edge_theta, rot_base, theta_base):
    """Per-tet component arrays: ``rot (9, 6, T)`` of the oriented ``R_p`` and ``th (3, 7, T)``
    of the seven ``θ̃`` (``index_select`` of edge tables, differentiable)."""
    E = edge_rot.shape[0]
    table = torch.cat((edge_rot.reshape(E, 9).t(), edge_rot.transpose(-1, -2).reshape(E, 9).t()), 0)
    rot = _soa_gather(table.reshape(-1), rot_base, 9, E)  # (9, 6, T)
    tt = edge_theta.permute(1, 2, 0).reshape(-1)  # (2, 3, E): θ̃_ij rows then θ̃_ji rows
    return rot, _soa_gather(tt, theta_base, 3, E)  # (3, 7, T)


def _unbind_tables(rot, th):
    """``R`` 6 x 9 and ``t`` 7 x 3 component tensors ``(T,)`` (views) of :func:`_soa_tables`."""
    return [[rot[q, p] for q in range(9)] for p in range(6)], [[th[c, k] for c in range(3)] for k in range(7)]


class _TetDDSoAFn(torch.autograd.Function):
    """Gather + closed form + scatter, component-major: ``(edge_rot (E,3,3), edge_theta (E,2,3)) -> (T,3)``.

    Every ``(T,)`` component is a contiguous array, so a 3x3 matrix-vector product is 9
    multiply-adds on contiguous memory (several times faster on CPU than batched 3x3 ``bmm``,
    which is itself several times faster than a broadcast multiply and a sum). The edge tables
    are laid out as ``(18, E)`` (``R`` then ``Rᵀ`` components) and ``(6, E)`` (``θ̃_ij`` then
    ``θ̃_ji``); the per-tet data is gathered with 9 + 3 ``index_select`` of ``(6T,)`` / ``(7T,)``
    and the backward scatters with ``index_add``.

    The backward is differentiable: when it is recorded (``create_graph=True``, i.e. grad mode
    on inside the backward: double backward, Hessian-vector products) it gathers the per-tet
    data and the forward intermediates again from the saved inputs and builds the gradient out
    of place (:class:`_OuterRecorded`), so autograd sees every dependence on ``edge_rot``,
    ``edge_theta`` and the incoming gradient; otherwise it reuses the tables saved by the
    forward and writes into preallocated buffers (:class:`_OuterInPlace`).
    """

    @staticmethod
    def forward(ctx, edge_rot, edge_theta, rot_base, theta_base):
        rot, th = _soa_tables(edge_rot, edge_theta, rot_base, theta_base)
        out, inter = _soa_forward(*_unbind_tables(rot, th))
        ctx.save_for_backward(edge_rot, edge_theta, rot, th, *[c for v in inter for c in v], rot_base, theta_base)
        return torch.stack(out, -1)

    @staticmethod
    def backward(ctx, g):
        saved = ctx.saved_tensors
        edge_rot, edge_theta, rot, th = saved[:4]
        rot_base, theta_base = saved[19], saved[20]
        E = edge_rot.shape[0]
        gc = tuple(g[:, i].contiguous() for i in range(3))
        if torch.is_grad_enabled():
            # a recorded backward: the saved tables carry no graph (the forward ran without
            # recording), so rebuild them and the intermediates from the inputs
            rot, th = _soa_tables(edge_rot, edge_theta, rot_base, theta_base)
            R, t = _unbind_tables(rot, th)
            _, inter = _soa_forward(R, t)
            sink = _OuterRecorded()
            vals = _soa_backward(R, t, inter, gc, sink)
            g_rot = torch.stack([torch.stack(sink.gR[p], 0) for p in range(6)], 1)  # (9, 6, T)
            g_th = torch.stack([torch.stack([vals[k][c] for k in range(7)], 0) for c in range(3)], 0)  # (3, 7, T)
        else:
            inter_flat = saved[4:19]
            inter = tuple(tuple(inter_flat[3 * k:3 * k + 3]) for k in range(5))
            R, t = _unbind_tables(rot, th)
            g_rot = torch.empty_like(rot)
            g_th = torch.empty_like(th)
            vals = _soa_backward(R, t, inter, gc, _OuterInPlace([[g_rot[q, p] for q in range(9)] for p in range(6)]))
            for k in range(7):
                for c in range(3):
                    g_th[c, k].copy_(vals[k][c])
        g_edge_rot = g_edge_theta = None
        if ctx.needs_input_grad[0]:
            gtab = _soa_scatter(g_rot, rot_base, 18, E).reshape(18, E)
            g_edge_rot = (gtab[:9].t() + gtab[9:].t().reshape(E, 3, 3).transpose(-1, -2).reshape(E, 9)
                          ).reshape(E, 3, 3)
        if ctx.needs_input_grad[1]:
            g_edge_theta = _soa_scatter(g_th, theta_base, 6, E).reshape(2, 3, E).permute(2, 0, 1)
        return g_edge_rot, g_edge_theta, None, None


def tet_dd_from_rotations(rot: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Closed-form ``𝔡∇ Alt 𝔡∇ Alt θ̃`` at ``[abcd]`` from per-tet gathered data: ``(T, 3)``.

    Args:
        rot: ``(T, 6, 3, 3)`` oriented ``R_ab, R_ac, R_ad, R_bc, R_bd, R_cd`` (pair_list(4)).
        theta: ``(T, 7, 3)`` ``θ̃_ba, θ̃_ca, θ̃_da, θ̃_cb, θ̃_db, θ̃_dc, θ̃_cd``.

    The end-of-Ch. 5 formula (:func:`torchconn.dec.dnabla.wedge_curvature_solder_tet`) regrouped by
    its leading transport, ``R_ab X_b + R_ac X_c + R_ad X_d`` with (fibers of ``b, c, d``)::

        X_b = R_bc (-θ̃_ca/6 + R_cd θ̃_db/6 - θ̃_cb/3 + θ̃_cd/2)
            + R_bd (-R_dc θ̃_cb/6 + θ̃_da/6 + θ̃_db/3 - θ̃_dc/2)
        X_c = (R_cb θ̃_ba - R_cd θ̃_da)/6 + θ̃_cb/2 - θ̃_cd/2
        X_d = (R_dc θ̃_ca - R_db θ̃_ba)/6 - (θ̃_db - θ̃_dc)/2

    Three rounds of batched matrix-vector products (6, then 2, then 3 per tet) instead of the
    8 matrix-matrix products and 16 matrix-vector products of the printed formula.
    Differentiated by plain autograd: the reference of the fused component-major kernel
    (``_TetDDSoAFn``, hand-written differentiable backward) that the mesh-level
    :func:`tet_dd_solder` uses.
    """
    return _tet_dd_forward(rot, theta)[0]


def tet_dd_solder(edge_rot: torch.Tensor, mesh, half_rot: torch.Tensor | None = None,
                  frames: torch.Tensor | None = None) -> torch.Tensor | None:
    """Averaged ``d∇d∇θ = 𝔡∇ Alt 𝔡∇ Alt θ̃`` on every tet of ``mesh``: ``(T, 3)`` at ``tets[t,0]``.

    Same value (to round-off) as the generic operators of
    :func:`torchconn.dec.dnabla.averaged_dd_solder` with the same arguments, without the dense
    ``(T, 4, 4, 3, 3)`` tables. ``None`` when the kernel does not apply (rotations or vertices
    not of rank 3). Arguments are not validated (the caller does that).

    Args:
        edge_rot: ``(E, 3, 3)`` ``R_ij`` of the canonical edges (read in ``frames`` if given).
        mesh: :class:`~torchconn.mesh.TetMesh`.
        half_rot: ``(E, 3, 3)`` ``√R_ij`` (in the vertex frames when ``frames`` is given);
            default :func:`torchconn.ops.so3.sqrt` (of ``F_i R_ij F_jᵀ`` with frames). For a
            connection given by skew parameters ``ω`` pass :func:`torchconn.ops.so3.half_exp`
            of ``ω``: no logarithm is needed.
        frames: ``(V, 3, 3)`` or ``None`` (conventions of
            :func:`torchconn.dec.dnabla.tet_solder_sqrt`: ``θ̃'_ij = F_iᵀ √R^amb_ij (v_j - v_i)``).
    """
    if edge_rot.shape[-1] != 3 or mesh.vertices.shape[-1] != 3:
        return None
    dev, dt = edge_rot.device, edge_rot.dtype
    k = tet_kernel(mesh, dev)
    e = mesh.edges.to(dev)
    verts = mesh.vertices.to(device=dev, dtype=dt)
    vec = verts[e[:, 1]] - verts[e[:, 0]]  # (E, 3) v_j - v_i
    if frames is None:
        H = _sqrt(edge_rot) if half_rot is None else half_rot
        theta = edge_solder_sqrt(H, vec)
    else:
        Fv = frames.to(device=dev, dtype=dt)
        Fi, Fj = Fv[e[:, 0]], Fv[e[:, 1]]
        H = _sqrt(Fi @ edge_rot @ Fj.transpose(-1, -2)) if half_rot is None \
            else Fi @ half_rot @ Fj.transpose(-1, -2)
        amb = edge_solder_sqrt(H, vec)  # (E, 2, 3) ambient
        theta = torch.stack((_matTvec(Fi, amb[:, 0]), _matTvec(Fj, amb[:, 1])), 1)
    return _TetDDSoAFn.apply(edge_rot, theta, k.rot_base, k.theta_base)
