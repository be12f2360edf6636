"""Face torsion of sorted-triangle meshes as an op (report Def. 3.2), and the per-edge gathers it shares.

The hot path, the √R torsion without frames, is the custom op
``torchconn::face_torsion_sqrt(edge_rot (*B, E, 3, 3), edge_vec (E, 3), face_index (3, F), inc_ptr,
inc) -> (*B, F, 3)``: ``Θ = √R_ab e_ab + R_ab √R_bc e_bc - √R_ac e_ac`` (``e_ij = v_j - v_i``), the
solder form ``θ̃_ij = √R_ij e_ij`` formed once per *edge* (``inc_ptr``, ``inc``: the edge-to-face
incidence of :func:`torchconn.ops.curvature._tables`). Its backward is the op
``torchconn::face_torsion_sqrt_backward`` (gradients for ``edge_rot`` and ``edge_vec``), whose
own autograd differentiates the generic backward formula (``torch.func.vjp``): double backward
and Hessian-vector products are exact. Kernels: generic = torch code (the root by the torch
formulas of :mod:`torchconn.ops._so3_formulas`); CPU = ``csrc/torsion.c`` when the switch allows:
the roots and ``θ̃`` per edge, the faces' sums, and a backward over *edges* that reads each edge's
incident faces from the incidence table (race-free, no atomics, no per-thread buffers), with the
root and its backward of ``csrc/so3.c``; no ``√R`` tensor, no ``(F, 3, 3)`` gather. Fake kernels
and vmap rules (batch = leading dim of ``edge_rot``/``grad``) as for every op of this package.

With frames (the frame-field loss) :func:`face_torsion` composes the so3 ops with torch
products (batched too); :func:`edge_frames` are the per-edge gathers the frame-field loss shares
between its ``tie`` and ``torsion`` terms. Both return ``None`` where they do not apply, and the
caller then evaluates its generic formula.
"""
from __future__ import annotations

import torch

import ctypes

from . import _so3_formulas as _f
from . import native as _native
from ._cache import edge_ends as _edge_ends
from ._cache import edge_vectors as _edge_vectors
from ._library import jvp as _library_jvp
from ._library import leading_vmap, qualname
from ._mat import _matTvec, _matvec
from .backend import can_use_compiled
from .curvature import _sorted_triangles
from .curvature import _tables as _face_tables
from .so3 import sqrt as _sqrt
from ..tolerances import get_eps

__all__ = ["edge_frames", "edge_solder_frames", "face_torsion"]


# ----------------------------------------------------------------------------- √R torsion op

def _combine(R, theta, face_index):
    """``Θ = θ̃_ab + R_ab θ̃_bc - θ̃_ac`` from per-edge ``θ̃ (*B, E, 3)``: ``(*B, F, 3)``."""
    F = face_index.shape[1]
    t = theta.index_select(-2, face_index.reshape(-1)).unflatten(-2, (3, F))  # (*B, 3, F, 3)
    Rab = R.index_select(-3, face_index[0])
    ab, bc, ac = t.unbind(-3)
    return ab - ac + _matvec(Rab, bc)


def _torsion_generic(R, vec, face_index, root=_f.sqrt):
    return _combine(R, _matvec(root(R), vec), face_index)


def _torsion_bwd_generic(R, vec, face_index, grad, root=_f.sqrt, root_bwd=_f.sqrt_bwd):
    """``(∂L/∂R (*B, E, 3, 3), ∂L/∂e (*B, E, 3))`` from ``grad = ∂L/∂Θ (*B, F, 3)``.

    ``∂L/∂θ̃_ab = G``, ``∂L/∂θ̃_bc = R_abᵀ G``, ``∂L/∂θ̃_ac = -G`` and ``∂L/∂R_ab ∋ G θ̃_bcᵀ``
    (``index_add`` onto the edges); then ``θ̃ = S e``: ``∂L/∂S = g_θ eᵀ``, ``∂L/∂e = Sᵀ g_θ``
    (per batch element: the caller sums over the batch) and ``∂L/∂R += sqrt_bwd(R, ∂L/∂S)``.
    """
    E = R.shape[-3]
    S = root(R)
    theta = _matvec(S, vec)
    fi = face_index
    Rab = R.index_select(-3, fi[0])
    t_bc = theta.index_select(-2, fi[1])
    g_th = torch.cat((grad, _matTvec(Rab, grad), -grad), -2)  # (*B, 3F, 3), rows ab, bc, ac
    zeros3 = grad.new_zeros((*R.shape[:-3], E, 3))
    g_theta = zeros3.index_add(-2, fi.reshape(-1), g_th)
    g_rab = grad.unsqueeze(-1) * t_bc.unsqueeze(-2)  # G θ̃_bcᵀ (*B, F, 3, 3)
    g_R = R.new_zeros(R.shape).index_add(-3, fi[0], g_rab)
    g_S = g_theta.unsqueeze(-1) * vec.unsqueeze(-2)
    return g_R + root_bwd(R, g_S), _matTvec(S, g_theta)


_I64, _P, _I32 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int32
_C_FWD = {dt: _native.declare("torsion", f"tor_fwd_{sfx}", [_P] * 4 + [_I64] * 3 + [ctypes.c_int, ctypes.c_double],
                              ctypes.c_int)
          for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}
_C_BWD = {dt: _native.declare("torsion", f"tor_bwd_{sfx}", [_P] * 8 + [_I64] * 3 + [ctypes.c_int, ctypes.c_double],
                              ctypes.c_int)
          for dt, sfx in ((torch.float32, "f32"), (torch.float64, "f64"))}


def _check_scratch(status: int) -> None:
    if status != 0:
        raise MemoryError("torchconn::face_torsion_sqrt: csrc/torsion.c could not map its scratch buffer")


def _c_ok(edge_rot, edge_vec, face_index, inc_ptr, inc, *more) -> bool:
    return (can_use_compiled("torsion", edge_rot, edge_vec, *more) and face_index.dtype == torch.int64
            and inc_ptr.dtype == inc.dtype == torch.int32)


def _c_sizes(edge_rot, face_index):
    E = edge_rot.shape[-3]
    return _I64(edge_rot.numel() // (9 * E) if E else 0), _I64(E), _I64(face_index.shape[1])


@torch.library.custom_op(qualname("face_torsion_sqrt_backward"), mutates_args=())
def _face_torsion_sqrt_backward(edge_rot: torch.Tensor, edge_vec: torch.Tensor, face_index: torch.Tensor,
                                inc_ptr: torch.Tensor, inc: torch.Tensor, grad: torch.Tensor
                                ) -> tuple[torch.Tensor, torch.Tensor]:
    return _torsion_bwd_generic(edge_rot, edge_vec, face_index, grad)


@_face_torsion_sqrt_backward.register_kernel("cpu")
def _(edge_rot, edge_vec, face_index, inc_ptr, inc, grad):
    if not _c_ok(edge_rot, edge_vec, face_index, inc_ptr, inc, grad):
        return _torsion_bwd_generic(edge_rot, edge_vec, face_index, grad)
    R, v, g = edge_rot.contiguous(), edge_vec.contiguous(), grad.contiguous()
    fi, ip, ic = face_index.contiguous(), inc_ptr.contiguous(), inc.contiguous()
    nb, E, F = _c_sizes(R, fi)
    g_rot = _native.empty(*R.shape, dtype=R.dtype)
    g_vec = _native.empty(*R.shape[:-2], 3, dtype=R.dtype)  # per batch element (the caller sums)
    if g_rot.numel():
        _check_scratch(_C_BWD[R.dtype](_native.ptr(R), _native.ptr(v), _native.ptr(fi), _native.ptr(ip),
                                       _native.ptr(ic), _native.ptr(g), _native.ptr(g_rot), _native.ptr(g_vec),
                                       nb, E, F, torch.get_num_threads(), get_eps("small_angle", R.dtype)))
    return g_rot, g_vec


@_face_torsion_sqrt_backward.register_fake
def _(edge_rot, edge_vec, face_index, inc_ptr, inc, grad):
    return (torch.empty_like(edge_rot, memory_format=torch.contiguous_format),
            edge_rot.new_empty((*edge_rot.shape[:-2], 3)))  # per batch element


def _tbwd_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _tbwd_backward(ctx, g_R, g_vec):
    edge_rot, edge_vec, face_index, inc_ptr, inc, grad = ctx.saved_tensors
    f = lambda r, v, g: _torsion_bwd_generic(r, v, face_index, g)  # noqa: E731
    _, vjp = torch.func.vjp(f, edge_rot, edge_vec, grad)
    gr, gv, gg = vjp((torch.zeros_like(edge_rot) if g_R is None else g_R,
                      torch.zeros_like(edge_vec) if g_vec is None else g_vec))
    return gr, gv, None, None, None, gg


_face_torsion_sqrt_backward.register_autograd(_tbwd_backward, setup_context=_tbwd_setup)


_face_torsion_sqrt_backward.register_vmap(leading_vmap(_face_torsion_sqrt_backward, "face_torsion_sqrt_backward",
                                                       batched=(0, 5), n_out=2))


def _sum_batch(g_vec: torch.Tensor, edge_vec: torch.Tensor) -> torch.Tensor:
    """``∂L/∂e`` of the op: the per-batch-element gradients summed (``edge_vec`` is shared)."""
    return g_vec.reshape(-1, *edge_vec.shape).sum(0) if g_vec.dim() > edge_vec.dim() else g_vec


@torch.library.custom_op(qualname("face_torsion_sqrt"), mutates_args=())
def _face_torsion_sqrt(edge_rot: torch.Tensor, edge_vec: torch.Tensor, face_index: torch.Tensor,
                       inc_ptr: torch.Tensor, inc: torch.Tensor) -> torch.Tensor:
    return _torsion_generic(edge_rot, edge_vec, face_index)


@_face_torsion_sqrt.register_kernel("cpu")
def _(edge_rot, edge_vec, face_index, inc_ptr, inc):
    if not _c_ok(edge_rot, edge_vec, face_index, inc_ptr, inc):
        return _torsion_generic(edge_rot, edge_vec, face_index)
    R, v, fi = edge_rot.contiguous(), edge_vec.contiguous(), face_index.contiguous()
    nb, E, F = _c_sizes(R, fi)
    out = _native.empty(*R.shape[:-3], fi.shape[1], 3, dtype=R.dtype)
    if out.numel():
        _check_scratch(_C_FWD[R.dtype](_native.ptr(R), _native.ptr(v), _native.ptr(fi), _native.ptr(out), nb, E, F,
                                       torch.get_num_threads(), get_eps("small_angle", R.dtype)))
    return out


@_face_torsion_sqrt.register_fake
def _(edge_rot, edge_vec, face_index, inc_ptr, inc):
    return edge_rot.new_empty((*edge_rot.shape[:-3], face_index.shape[1], 3))


def _t_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _t_backward(ctx, grad):
    edge_rot, edge_vec, face_index, inc_ptr, inc = ctx.saved_tensors
    g_R, g_vec = _face_torsion_sqrt_backward(edge_rot, edge_vec, face_index, inc_ptr, inc, grad)
    return g_R, _sum_batch(g_vec, edge_vec), None, None, None


_face_torsion_sqrt.register_autograd(_t_backward, setup_context=_t_setup)
_face_torsion_sqrt.register_vmap(leading_vmap(_face_torsion_sqrt, "face_torsion_sqrt", batched=(0,)))


class _TorsionFn(torch.autograd.Function):
    """The op for the ``torch.func`` transforms (see :class:`torchconn.ops.curvature._CurvatureFn`)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(edge_rot, edge_vec, face_index, inc_ptr, inc):
        return _face_torsion_sqrt(edge_rot, edge_vec, face_index, inc_ptr, inc)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(*inputs)
        ctx.save_for_forward(*inputs)

    @staticmethod
    def backward(ctx, grad):
        edge_rot, edge_vec, face_index, inc_ptr, inc = ctx.saved_tensors
        g_R, g_vec = _TorsionBwdFn.apply(edge_rot, edge_vec, face_index, inc_ptr, inc, grad)
        return g_R, _sum_batch(g_vec, edge_vec), None, None, None

    @staticmethod
    def jvp(ctx, t_rot, t_vec, *_):
        edge_rot, edge_vec, face_index, _, _ = ctx.saved_tensors
        t_vec = torch.zeros_like(edge_vec) if t_vec is None else t_vec
        f = lambda r, v: _torsion_generic(r, v, face_index)  # noqa: E731
        return _library_jvp(f, (edge_rot, edge_vec), (t_rot, t_vec))


class _TorsionBwdFn(torch.autograd.Function):
    generate_vmap_rule = True

    @staticmethod
    def forward(edge_rot, edge_vec, face_index, inc_ptr, inc, grad):
        return _face_torsion_sqrt_backward(edge_rot, edge_vec, face_index, inc_ptr, inc, grad)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(*inputs)
        ctx.save_for_forward(*inputs)

    @staticmethod
    def backward(ctx, g_R, g_vec):
        return _tbwd_backward(ctx, g_R, g_vec)

    @staticmethod
    def jvp(ctx, t_rot, t_vec, _fi, _ip, _ic, t_grad):
        edge_rot, edge_vec, face_index, _, _, grad = ctx.saved_tensors
        f = lambda r, v, g: _torsion_bwd_generic(r, v, face_index, g)  # noqa: E731
        z = torch.zeros_like
        t = (z(edge_rot) if t_rot is None else t_rot, z(edge_vec) if t_vec is None else t_vec,
             z(grad) if t_grad is None else t_grad)
        return _library_jvp(f, (edge_rot, edge_vec, grad), t)


def face_torsion_sqrt(edge_rot: torch.Tensor, edge_vec: torch.Tensor, face_index: torch.Tensor,
                      inc_ptr: torch.Tensor, inc: torch.Tensor) -> torch.Tensor:
    """``torchconn::face_torsion_sqrt`` (module doc): ``(*B, E, 3, 3), (E, 3), (3, F)`` and the
    incidence table ``inc_ptr (E + 1)``, ``inc (3F)`` int32 -> ``(*B, F, 3)``."""
    if torch.compiler.is_compiling():
        return _face_torsion_sqrt(edge_rot, edge_vec, face_index, inc_ptr, inc)
    return _TorsionFn.apply(edge_rot, edge_vec, face_index, inc_ptr, inc)


# ----------------------------------------------------------------------------- gathers, frames

def edge_frames(edge_rot: torch.Tensor, mesh, frames: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Per-edge frame gathers and the transported frame, shared by the frame-field loss terms.

    Args:
        edge_rot: ``(*B, E, 3, 3)`` ``R_ij`` of the canonical edges ``mesh.edges (E, 2)``.
        frames: ``(*B, V, 3, 3)`` (columns = frame axes in world coordinates).

    Returns:
        ``(F_i, F_i R_ij, F_j)``, each ``(*B, E, 3, 3)``. ``index_select`` (backward:
        ``index_add_``) rather than advanced indexing (backward: accumulating ``index_put_``).
        ``None`` unless ``mesh`` has sorted triangles and ``edge_rot`` is ``(*B, E, 3, 3)``.
    """
    if not (_sorted_triangles(mesh) and edge_rot.dim() >= 3 and edge_rot.shape[-1] == 3):
        return None
    i, j = _edge_ends(mesh, edge_rot.device)
    Fi, Fj = frames.index_select(-3, i), frames.index_select(-3, j)
    return Fi, Fi @ edge_rot, Fj


def edge_solder_frames(edge_rot: torch.Tensor, mesh, kind: str = "sqrt",
                       frames: torch.Tensor | None = None,
                       edge_frame_rot: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
                       ) -> torch.Tensor:
    """Solder form of each canonical edge ``(i, j)`` in the fiber of ``i``: ``(*B, E, 3)``.

    ``kind="sqrt"``: ``θ̃_ij = √R_ij (v_j - v_i)`` (report Def. 3.2); ``"naive"``: ``v_j - v_i``.
    With ``frames (*B, V, 3, 3)`` the conventions of :func:`torchconn.dec.torsion.face_torsion`:
    the root is taken of the ambient ``F_i R_ij F_jᵀ`` and the value is expressed in ``F_i``,
    ``θ̃'_ij = F_iᵀ √(F_i R_ij F_jᵀ) (v_j - v_i)``. ``edge_frame_rot``: the triple
    ``(F_i, F_i R_ij, F_j)`` of :func:`edge_frames` when the caller has it already (the same
    values; saves the gathers and one product).
    """
    vec = _edge_vectors(mesh, edge_rot.device, edge_rot.dtype)
    if frames is None and edge_frame_rot is None:
        # the cached edge vectors are never handed out: a copy for the naive solder form
        return _matvec(_sqrt(edge_rot), vec) if kind == "sqrt" else vec.expand(*edge_rot.shape[:-2], 3).clone()
    if edge_frame_rot is None:
        i, j = _edge_ends(mesh, edge_rot.device)
        Fi, Fj = frames.index_select(-3, i), frames.index_select(-3, j)
        FiR = Fi @ edge_rot if kind == "sqrt" else None
    else:
        Fi, FiR, Fj = edge_frame_rot
    if kind == "sqrt":
        vec = _matvec(_sqrt(FiR @ Fj.transpose(-1, -2)), vec)
    return _matTvec(Fi, vec)


def face_torsion(edge_rot: torch.Tensor, mesh, kind: str = "sqrt", frames: torch.Tensor | None = None,
                 cut=-1, edge_frame_rot: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
                 ) -> torch.Tensor | None:
    """Torsion of every sorted face ``[a<b<c]`` with cut ``c``: ``(*B, F, 3)`` in the fiber of ``a``.

    ``Θ = θ̃_ab + R_ab θ̃_bc - θ̃_ac`` (Def. 3.2: prongs ``a -> b -> c`` and ``a -> c``), with the
    per-edge solder form of :func:`edge_solder_frames` formed once per *edge*; ``edge_rot``
    ``(*B, E, 3, 3)`` with any leading batch dimensions. ``kind="sqrt"`` without frames is the
    op ``torchconn::face_torsion_sqrt`` (module doc). Equals the generic loop formula of
    :func:`torchconn.dec.torsion.face_torsion` with ``cut=-1`` (with frames,
    ``F_aᵀ Θ^amb = F_aᵀ θ̃^amb_ab + R_ab F_bᵀ θ̃^amb_bc - F_aᵀ θ̃^amb_ac`` since
    ``R^amb_ab = F_a R_ab F_bᵀ``). ``frames`` is converted to the dtype and device of
    ``edge_rot``. ``edge_frame_rot``: optional ``(F_i, F_i R_ij, F_j)`` from
    :func:`edge_frames` (replaces ``frames``; the frame-field loss shares it with its ``tie``
    term). ``None`` unless ``mesh`` has sorted triangles and ``cut`` is ``-1`` or ``2``;
    ``edge_rot`` with another number of rows than ``mesh.edges`` raises ``ValueError``.
    """
    if not (_sorted_triangles(mesh) and type(cut) is int and cut in (-1, 2)):
        return None
    E = int(mesh.edges.shape[0])
    if edge_rot.dim() < 3 or edge_rot.shape[-3:] != (E, 3, 3):
        raise ValueError(f"face_torsion: edge_rot must have shape ({E}, 3, 3) (after optional leading batch dims), "
                         f"one rotation per mesh edge in mesh.edges order, got {tuple(edge_rot.shape)}")
    fi, inc_ptr, inc = _face_tables(mesh, edge_rot.device)
    if kind == "sqrt" and frames is None and edge_frame_rot is None:
        return face_torsion_sqrt(edge_rot, _edge_vectors(mesh, edge_rot.device, edge_rot.dtype), fi, inc_ptr, inc)
    if frames is not None:
        frames = frames.to(edge_rot)
    th = edge_solder_frames(edge_rot, mesh, kind, frames, edge_frame_rot)
    return _combine(edge_rot, th, fi)
