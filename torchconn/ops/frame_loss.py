"""The compiled frame-field loss terms ``smooth``, ``tie``, ``flat``, ``torsion`` as one op.

``csrc/frame_loss.c`` computes the four means (definitions: :mod:`torchconn.frames.loss`) *and*
the gradient of their weighted sum in one sweep over the edges and faces.
:func:`frame_loss_terms` is the op :class:`torchconn.frames.loss.FrameFieldLoss` calls; it
returns ``None`` where the compiled kernel cannot run (see :func:`frame_loss_terms`), and the
caller then evaluates its torch terms. The index and geometry tables and the scratch buffers
of the kernel are built once per mesh (``mesh.require``).
"""
from __future__ import annotations

import ctypes
from typing import Mapping

import torch

from . import native as _native
from ._cache import require as _require
from .backend import can_use_compiled
from .curvature import _sorted_triangles

__all__ = ["COMPILED_TERMS", "frame_loss_terms"]

#: Terms computed by ``csrc/frame_loss.c``, in the order of its flag bits (bit 4: gradient).
COMPILED_TERMS = ("smooth", "tie", "flat", "torsion")
_GRAD = 16


_CREATE_GRAPH_ERROR = (
    "torchconn.ops.frame_loss: the compiled frame-field loss kernel (csrc/frame_loss.c, terms "
    f"{', '.join(COMPILED_TERMS)}) computes a first-order gradient only and cannot be differentiated "
    "again (create_graph=True, double backward, a Hessian-vector product); evaluate the loss with the "
    "compiled kernels off, `with torchconn.ops.compiled(False): out = loss(edge_rot, frames)`, whose torch "
    "terms give exact higher-order gradients")


class _CompiledFrameLossFn(torch.autograd.Function):
    """``(edge_rot (E,3,3), frames (V,3,3)) -> (4,)`` values of smooth, tie, flat, torsion.

    The terms are scalar means, so the gradient of ``sum_k w_k term_k`` (``w`` = the loss
    weights) is known in the forward pass. The backward scales that saved gradient when the
    incoming weights are proportional to ``w`` (the usual ``out["total"].backward()``) and
    otherwise re-runs the kernel with the incoming weights, so any combination of the returned
    terms differentiates exactly. Same values as the torch terms to round-off (a term that is
    off returns 0). The √R of the torsion term is the closed form
    ``I + (A - Aᵀ)/(4c) + (A + Aᵀ - 2I)/(4(1+c))``, ``c = cos(angle/2)``, equal to
    :func:`torchconn.ops.so3.sqrt` on rotations; its gradient agrees with the torch path along
    rotations (the tangent directions a parametrization through ``so3.exp`` sees), not for
    arbitrary off-manifold perturbations of the matrices.

    First order only: the gradient comes out of the C sweep as numbers, so a recorded backward
    (``create_graph=True``: double backward, ``autograd.grad(..., create_graph=True)``,
    Hessian-vector products; detected as grad mode on inside the backward) raises
    ``RuntimeError`` rather than return a gradient without its own derivative. Whether the
    graph will be recorded is only known at backward time, and the torch terms live above
    this layer (:mod:`torchconn.frames.loss`), so the caller switches the kernel off for
    higher-order gradients (:func:`torchconn.ops.compiled`).
    """

    @staticmethod
    def forward(ctx, edge_rot, frames, group, mesh, flags, wts, power, eps):
        sums, gR, gF = _run(mesh, edge_rot, frames, group, flags, wts, power, eps)
        if flags & _GRAD:
            ctx.save_for_backward(edge_rot, frames, group, gR, gF)
            ctx.mesh, ctx.flags, ctx.wts, ctx.power, ctx.eps = mesh, flags, wts, power, eps
        return sums[:4].to(edge_rot.dtype)

    @staticmethod
    def backward(ctx, g):
        if torch.is_grad_enabled():
            raise RuntimeError(_CREATE_GRAPH_ERROR)
        edge_rot, frames, group, gR, gF = ctx.saved_tensors
        gv = [float(x) for x in g.to(torch.float64)]
        on = [b for b in range(4) if ctx.flags & (1 << b)]
        ref = next((b for b in on if ctx.wts[b] != 0.0), None)
        scale = gv[ref] / ctx.wts[ref] if ref is not None else 0.0
        tol = 1e-12 if edge_rot.dtype == torch.float64 else 1e-6
        if all(abs(gv[b] - scale * ctx.wts[b]) <= tol * max(abs(gv[b]), abs(scale * ctx.wts[b])) for b in on):
            dR, dF = (gR, gF) if scale == 1.0 else (gR * scale, gF * scale)
        else:  # another combination of the terms: one more sweep with the incoming weights
            _, dR, dF = _run(ctx.mesh, edge_rot, frames, group, ctx.flags, gv, ctx.power, ctx.eps)
        return (dR if ctx.needs_input_grad[0] else None, dF if ctx.needs_input_grad[1] else None,
                None, None, None, None, None, None)


def _buffers(mesh, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """Index and geometry tables of ``csrc/frame_loss.c`` for ``dtype`` (CPU, built once per mesh)."""

    def build(m):
        e = m.edges.to("cpu", torch.int64).contiguous()
        verts = m.vertices.to("cpu", torch.float64)
        p = m.vertices[m.faces]
        area = 0.5 * torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], dim=-1).norm(dim=-1)
        return {
            "edges": e,
            "fidx": m.face_edges.to("cpu", torch.int64)[:, [2, 0, 1]].contiguous(),  # ab, bc, ac
            "vec": (verts[e[:, 1]] - verts[e[:, 0]]).to(dtype).contiguous(),
            "area": area.to("cpu", dtype).contiguous(),
        }

    return _require(mesh, f"ops.frame_loss.buffers.{dtype}", build)


def _workspace(mesh, dtype: torch.dtype, nt: int) -> dict[str, torch.Tensor]:
    """Scratch buffers of ``csrc/frame_loss.c`` for ``nt`` threads (kept: no page faults per step)."""

    def build(m):
        E, V = int(m.edges.shape[0]), int(m.vertices.shape[0])
        need = max(1, (nt - 1) * (12 * E + 9 * V))
        return {"work": torch.empty(need, dtype=dtype), "theta": torch.empty(E, 3, dtype=dtype),
                "gtheta": torch.empty(E, 3, dtype=dtype), "unrel": torch.empty(E, dtype=torch.uint8)}

    return _require(mesh, f"ops.frame_loss.workspace.{dtype}.{nt}", build)


def _run(mesh, edge_rot: torch.Tensor, frames: torch.Tensor, group: torch.Tensor, flags: int, wts,
         power: float, eps: float):
    """Run ``csrc/frame_loss.c``: ``(sums (5,) float64, gR (E,3,3) | None, gF (V,3,3) | None)``."""
    dt = edge_rot.dtype
    E, V, F = edge_rot.shape[0], frames.shape[0], mesh.faces.shape[0]
    grad = bool(flags & _GRAD)
    nt = max(1, torch.get_num_threads())
    buf = _buffers(mesh, dt)
    ws = _workspace(mesh, dt, nt if grad else 1)
    sums = torch.zeros(5, dtype=torch.float64)
    w64 = torch.tensor([float(x) for x in wts] + [0.0] * (4 - len(wts)), dtype=torch.float64)
    gR = edge_rot.new_empty(E, 3, 3) if grad else None
    gF = frames.new_empty(V, 3, 3) if grad else None
    vp, long_, int_, dbl = ctypes.c_void_p, ctypes.c_long, ctypes.c_int, ctypes.c_double
    fn = _native.function("frame_loss", "frame_loss_f64" if dt == torch.float64 else "frame_loss_f32",
                          [long_, long_, long_, int_] + [vp] * 7 + [int_, dbl, dbl] + [vp] * 8, ctypes.c_int)
    P, nul = _native.ptr, ctypes.c_void_p(None)
    status = fn(ctypes.c_long(E), ctypes.c_long(V), ctypes.c_long(F), ctypes.c_int(nt),
                P(edge_rot), P(frames), P(buf["edges"]), P(buf["fidx"]), P(buf["vec"]), P(buf["area"]),
                P(group), ctypes.c_int(flags), ctypes.c_double(power), ctypes.c_double(eps),
                P(w64), P(sums), P(gR) if grad else nul, P(gF) if grad else nul, P(ws["work"]),
                P(ws["theta"]), P(ws["gtheta"]), P(ws["unrel"]))
    if status != 0:
        raise RuntimeError(f"csrc/frame_loss.c returned {status}: its octahedral score table does not match "
                           "the group table passed in (torchconn.frames.octahedral.group())")
    return sums, gR, gF


def frame_loss_terms(edge_rot: torch.Tensor, frames: torch.Tensor, mesh, group: torch.Tensor,
                     weights: Mapping[str, float], smooth_power: float, smooth_eps: float
                     ) -> dict[str, torch.Tensor] | None:
    """The weighted-on terms of :data:`COMPILED_TERMS` by the compiled kernel, or ``None``.

    Args:
        edge_rot: ``(E, 3, 3)`` ``R_ij`` of the canonical edges of ``mesh``.
        frames: ``(V, 3, 3)``.
        mesh: a mesh with sorted triangles (``TetMesh``).
        group: ``(24, 3, 3)`` the octahedral group in the order of
            :func:`torchconn.frames.octahedral.group` (the kernel checks its written-out scores
            against it and raises ``RuntimeError`` on a mismatch).
        weights: term name -> weight; terms of weight 0 are not computed (``tie`` runs with
            ``torsion``: it supplies the mask).
        smooth_power, smooth_eps: ``rho`` of the ``smooth`` and ``tie`` terms.

    Returns:
        ``{term: 0-dim tensor}`` for the terms with non-zero weight (differentiable, first
        order), or ``None`` when the kernel cannot run: no such term, a mesh without sorted
        triangles, shapes other than ``(E, 3, 3)`` / ``(V, 3, 3)``, or
        :func:`torchconn.ops.backend.can_use_compiled` false. A recorded backward
        (``create_graph``) through these terms raises ``RuntimeError``: switch the kernel off
        (``with torchconn.ops.compiled(False):``) for higher-order gradients.
    """
    if not any(weights.get(k, 0.0) for k in COMPILED_TERMS):
        return None
    if not (_sorted_triangles(mesh) and edge_rot.dim() == 3 and tuple(edge_rot.shape[1:]) == (3, 3)
            and frames.dim() == 3 and tuple(frames.shape[1:]) == (3, 3)
            and edge_rot.shape[0] == mesh.edges.shape[0] and frames.shape[0] == mesh.vertices.shape[0]
            and can_use_compiled("frame_loss", edge_rot, frames)):
        return None
    flags = sum(1 << b for b, k in enumerate(COMPILED_TERMS) if weights.get(k, 0.0))
    if weights.get("torsion", 0.0):
        flags |= 2  # the torsion mask comes from the tie matching (as in the torch path)
    if torch.is_grad_enabled() and (edge_rot.requires_grad or frames.requires_grad):
        flags |= _GRAD
    wts = [float(weights.get(k, 0.0)) if flags & (1 << b) else 0.0 for b, k in enumerate(COMPILED_TERMS)]
    table = group.to("cpu", torch.float64).reshape(24, 9).contiguous()
    vals = _CompiledFrameLossFn.apply(edge_rot.contiguous(), frames.contiguous(), table, mesh, flags, wts,
                                      float(smooth_power), float(smooth_eps))
    return {k: vals[b] for b, k in enumerate(COMPILED_TERMS) if flags & (1 << b)}
