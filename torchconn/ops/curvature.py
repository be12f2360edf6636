"""Face curvature of sorted-triangle meshes as a custom op (report Sec. 3.2, (3.2.1)).

``torchconn::face_curvature(edge_rot (*B, E, 3, 3), face_index (3, F), inc_ptr (E + 1),
inc (3F), kind) -> (*B, F, 3, 3)``, with the backward op ``torchconn::face_curvature_backward``
(same tables, plus ``grad``). ``face_index`` lists the canonical edges ``ab, bc, ac`` of every
sorted face ``[a<b<c]``; ``inc_ptr``/``inc`` is the per-edge CSR table of the incident
``(face, slot)`` pairs (``3 f + slot``) that the compiled backward sums over (race-free, no
atomics; the generic backward uses ``index_add`` and ignores it). The tables are built once per
mesh (:func:`torchconn.ops._cache.require`). ``kind`` is 2 (cut ``c``), 1 (cut ``b``) or 0
(holonomy).

Kernels: the default (every device, dtype) is the fused torch code: gather by ``index_select``,
written-out 3x3 products on unbound components, component-major; the CPU kernel runs
``csrc/curvature.c`` (OpenMP over faces forward and over edges backward, float32/float64,
batch looped in C) when :func:`torchconn.ops.backend.can_use_compiled` allows. The backward
op's own autograd differentiates the generic backward formula (``torch.func.vjp``; it is
linear in ``grad`` and bilinear in the rotations), so double backward, ``create_graph`` and
Hessian-vector products are exact on every path. Fake kernels give the shapes; the vmap rules
take the batch as a leading dimension of ``edge_rot`` (and ``grad``).

:func:`face_curvature` is what :func:`torchconn.dec.curvature.face_curvature` (the public
entry point) calls; it returns ``None`` where it does not apply (a mesh without sorted
triangles, a non-integer cut), and the caller then evaluates its generic loop formula.
"""
from __future__ import annotations

from ctypes import c_int, c_long, c_void_p

import torch

from . import native as _native
from ._cache import require as _require
from ._cache import traced_constant
from ._library import jvp as _library_jvp
from ._library import leading_vmap, qualname
from .backend import can_use_compiled

__all__ = ["face_curvature"]

_SUF = {torch.float32: "f32", torch.float64: "f64"}
_C_FWD = {dt: _native.declare("curvature", f"curv_fwd_{s}",
                              [c_void_p, c_void_p, c_void_p, c_long, c_long, c_long, c_int, c_int])
          for dt, s in _SUF.items()}
_C_BWD = {dt: _native.declare("curvature", f"curv_bwd_{s}",
                              [c_void_p] * 6 + [c_long, c_long, c_long, c_int, c_int])
          for dt, s in _SUF.items()}


def _sorted_triangles(mesh) -> bool:
    """A tet mesh (or its ``nn.MeshBuffers``): sorted faces ``[a<b<c]`` with ``face_edges``.

    Read from the mesh's ``kind`` attribute (:class:`torchconn.mesh.base.MeshBase`): ops sits
    below the mesh layer and does not import its classes."""
    return getattr(mesh, "kind", None) == "tet"


# ----------------------------------------------------------------------------- generic formulas

def _mm(A, B):
    """``A B`` on unbound row-major components (9 tensors each)."""
    return tuple(torch.addcmul(torch.addcmul(A[3 * i] * B[j], A[3 * i + 1], B[3 + j]), A[3 * i + 2], B[6 + j])
                 for i in range(3) for j in range(3))


def _tr(A):
    """Transpose of unbound row-major components (a relabeling, no arithmetic)."""
    return tuple(A[3 * j + i] for i in range(3) for j in range(3))


def _face_formula(kind: int, ab, bc, ac):
    """Curvature of ``[a<b<c]`` on components: kind 2 (cut c), 1 (cut b), 0 (holonomy, no ``- I``)."""
    if kind == 2:
        return tuple(x - y for x, y in zip(_mm(ab, bc), ac))
    if kind == 1:
        return tuple(x - y for x, y in zip(ab, _mm(ac, _tr(bc))))
    return _mm(_mm(ab, bc), _tr(ac))


def _gather(edge_rot: torch.Tensor, face_index: torch.Tensor):
    """``(ab, bc, ac)``, each 9 components ``(N, F)`` of the rotations of every face, ``N`` the flat batch."""
    E, F = edge_rot.shape[-3], face_index.shape[1]
    table = edge_rot.reshape(-1, E, 9).permute(2, 0, 1)  # (9, N, E) view
    g = table.index_select(2, face_index.reshape(-1)).unflatten(2, (3, F))  # (9, N, 3, F)
    return tuple(tuple(g[q, :, k] for q in range(9)) for k in range(3))


def _curvature_generic(edge_rot: torch.Tensor, face_index: torch.Tensor, kind: int) -> torch.Tensor:
    """``(*B, E, 3, 3) -> (*B, F, 3, 3)``, the formulas of the module doc in torch operations."""
    ab, bc, ac = _gather(edge_rot, face_index)
    H = _face_formula(kind, ab, bc, ac)
    if kind == 0:
        H = tuple(h - 1.0 if q in (0, 4, 8) else h for q, h in enumerate(H))
    out = torch.stack(H, -1)  # (N, F, 9)
    return out.reshape(*edge_rot.shape[:-3], face_index.shape[1], 3, 3)


def _curvature_bwd_generic(edge_rot: torch.Tensor, grad: torch.Tensor, face_index: torch.Tensor,
                           kind: int) -> torch.Tensor:
    """``∂L/∂edge_rot (*B, E, 3, 3)`` from ``grad = ∂L/∂H (*B, F, 3, 3)`` (``index_add`` onto the edges).

    With ``G = ∂L/∂H``: cut c ``G R_bcᵀ, R_abᵀ G, -G``; cut b ``G, -Gᵀ R_ac, -G R_bc``;
    holonomy (``P = R_ab R_bc``) ``(G R_ac) R_bcᵀ, R_abᵀ (G R_ac), Gᵀ P``.
    """
    E, F = edge_rot.shape[-3], face_index.shape[1]
    ab, bc, ac = _gather(edge_rot, face_index)
    Gt = grad.reshape(-1, F, 9).permute(2, 0, 1)  # (9, N, F)
    G = tuple(Gt[q] for q in range(9))
    if kind == 2:
        gab, gbc, gac = _mm(G, _tr(bc)), _mm(_tr(ab), G), tuple(-x for x in G)
    elif kind == 1:
        gab, gbc, gac = G, tuple(-x for x in _mm(_tr(G), ac)), tuple(-x for x in _mm(G, bc))
    else:
        GR = _mm(G, ac)
        gab, gbc, gac = _mm(GR, _tr(bc)), _mm(_tr(ab), GR), _mm(_tr(G), _mm(ab, bc))
    vals = torch.stack([torch.stack((gab[q], gbc[q], gac[q]), 1) for q in range(9)], 0)  # (9, N, 3, F)
    N = vals.shape[1]
    out = vals.new_zeros(9, N, E).index_add(2, face_index.reshape(-1), vals.reshape(9, N, 3 * F))
    return out.permute(1, 2, 0).contiguous().reshape(edge_rot.shape)  # the fake's (contiguous) layout


# ----------------------------------------------------------------------------- compiled

def _curvature_c(edge_rot, face_index, kind):
    E, F = edge_rot.shape[-3], face_index.shape[1]
    batch = edge_rot.shape[:-3]
    N = batch.numel()
    out = _native.empty(*batch, F, 3, 3, dtype=edge_rot.dtype)
    if N and F:
        src, idx = edge_rot.contiguous(), face_index.contiguous()  # kept alive until the call returns
        _C_FWD[edge_rot.dtype](_native.ptr(src), _native.ptr(idx), _native.ptr(out), N, E, F, kind,
                               torch.get_num_threads())
    return out


def _curvature_bwd_c(edge_rot, grad, face_index, inc_ptr, inc, kind):
    E, F = edge_rot.shape[-3], face_index.shape[1]
    N = edge_rot.shape[:-3].numel()
    out = _native.empty(*edge_rot.shape, dtype=edge_rot.dtype)
    if N and E:
        ts = [t.contiguous() for t in (edge_rot, grad, face_index, inc_ptr, inc)]
        _C_BWD[edge_rot.dtype](*(_native.ptr(t) for t in ts), _native.ptr(out), N, E, F, kind,
                               torch.get_num_threads())
    return out


def _c_ok(*tensors) -> bool:
    return can_use_compiled("curvature", *tensors)


# ----------------------------------------------------------------------------- the ops

@torch.library.custom_op(qualname("face_curvature_backward"), mutates_args=())
def _face_curvature_backward(edge_rot: torch.Tensor, grad: torch.Tensor, face_index: torch.Tensor,
                             inc_ptr: torch.Tensor, inc: torch.Tensor, kind: int) -> torch.Tensor:
    return _curvature_bwd_generic(edge_rot, grad, face_index, kind)


@_face_curvature_backward.register_kernel("cpu")
def _(edge_rot, grad, face_index, inc_ptr, inc, kind):
    if _c_ok(edge_rot, grad):
        return _curvature_bwd_c(edge_rot, grad, face_index, inc_ptr, inc, kind)
    return _curvature_bwd_generic(edge_rot, grad, face_index, kind)


@_face_curvature_backward.register_fake
def _(edge_rot, grad, face_index, inc_ptr, inc, kind):
    return torch.empty_like(edge_rot, memory_format=torch.contiguous_format)


def _bwd_setup(ctx, inputs, output):
    edge_rot, grad, face_index, _, _, kind = inputs
    ctx.save_for_backward(edge_rot, grad, face_index)
    ctx.kind = kind


def _bwd_backward(ctx, gg):
    edge_rot, grad, face_index = ctx.saved_tensors
    _, vjp = torch.func.vjp(lambda r, g: _curvature_bwd_generic(r, g, face_index, ctx.kind), edge_rot, grad)
    g_rot, g_grad = vjp(gg)
    return g_rot, g_grad, None, None, None, None


_face_curvature_backward.register_autograd(_bwd_backward, setup_context=_bwd_setup)
_face_curvature_backward.register_vmap(leading_vmap(_face_curvature_backward, "face_curvature_backward",
                                                    batched=(0, 1)))


@torch.library.custom_op(qualname("face_curvature"), mutates_args=())
def _face_curvature(edge_rot: torch.Tensor, face_index: torch.Tensor, inc_ptr: torch.Tensor,
                    inc: torch.Tensor, kind: int) -> torch.Tensor:
    return _curvature_generic(edge_rot, face_index, kind)


@_face_curvature.register_kernel("cpu")
def _(edge_rot, face_index, inc_ptr, inc, kind):
    if _c_ok(edge_rot):
        return _curvature_c(edge_rot, face_index, kind)
    return _curvature_generic(edge_rot, face_index, kind)


@_face_curvature.register_fake
def _(edge_rot, face_index, inc_ptr, inc, kind):
    return edge_rot.new_empty((*edge_rot.shape[:-3], face_index.shape[1], 3, 3))


def _fwd_setup(ctx, inputs, output):
    edge_rot, face_index, inc_ptr, inc, kind = inputs
    ctx.save_for_backward(edge_rot, face_index, inc_ptr, inc)
    ctx.kind = kind


def _fwd_backward(ctx, grad):
    edge_rot, face_index, inc_ptr, inc = ctx.saved_tensors
    return _face_curvature_backward(edge_rot, grad, face_index, inc_ptr, inc, ctx.kind), None, None, None, None


_face_curvature.register_autograd(_fwd_backward, setup_context=_fwd_setup)
_face_curvature.register_vmap(leading_vmap(_face_curvature, "face_curvature", batched=(0,)))


class _CurvatureFn(torch.autograd.Function):
    """The op for the ``torch.func`` transforms (``register_autograd`` lacks ``setup_context``,
    pytorch/pytorch#168393): forward and backward are the two ops, the second derivative and
    ``jvp`` are ``torch.func`` of the generic formulas; used eagerly (see :mod:`.so3`)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(edge_rot, face_index, inc_ptr, inc, kind):
        return _face_curvature(edge_rot, face_index, inc_ptr, inc, kind)

    @staticmethod
    def setup_context(ctx, inputs, output):
        edge_rot, face_index, inc_ptr, inc, kind = inputs
        ctx.save_for_backward(edge_rot, face_index, inc_ptr, inc)
        ctx.save_for_forward(edge_rot)
        ctx.kind, ctx.face_index = kind, face_index

    @staticmethod
    def backward(ctx, grad):
        edge_rot, face_index, inc_ptr, inc = ctx.saved_tensors
        return _CurvatureBwdFn.apply(edge_rot, grad, face_index, inc_ptr, inc, ctx.kind), None, None, None, None

    @staticmethod
    def jvp(ctx, t_rot, *_):
        (edge_rot,) = ctx.saved_tensors[:1]
        f = lambda r: _curvature_generic(r, ctx.face_index, ctx.kind)  # noqa: E731
        return _library_jvp(f, (edge_rot,), (t_rot,))


class _CurvatureBwdFn(torch.autograd.Function):
    generate_vmap_rule = True

    @staticmethod
    def forward(edge_rot, grad, face_index, inc_ptr, inc, kind):
        return _face_curvature_backward(edge_rot, grad, face_index, inc_ptr, inc, kind)

    @staticmethod
    def setup_context(ctx, inputs, output):
        edge_rot, grad, face_index, _, _, kind = inputs
        ctx.save_for_backward(edge_rot, grad)
        ctx.save_for_forward(edge_rot, grad)
        ctx.kind, ctx.face_index = kind, face_index

    @staticmethod
    def backward(ctx, gg):
        edge_rot, grad = ctx.saved_tensors
        f = lambda r, g: _curvature_bwd_generic(r, g, ctx.face_index, ctx.kind)  # noqa: E731
        g_rot, g_grad = torch.func.vjp(f, edge_rot, grad)[1](gg)
        return g_rot, g_grad, None, None, None, None

    @staticmethod
    def jvp(ctx, t_rot, t_grad, *_):
        edge_rot, grad = ctx.saved_tensors
        f = lambda r, g: _curvature_bwd_generic(r, g, ctx.face_index, ctx.kind)  # noqa: E731
        return _library_jvp(f, (edge_rot, grad), (t_rot, t_grad))


# ----------------------------------------------------------------------------- tables, public

@traced_constant
def _tables(mesh, device):
    """``(face_index (3, F) int64, inc_ptr (E + 1) int32, inc (3F) int32)`` on ``device``, once per mesh
    (built eagerly on the real mesh, also when asked while ``torch.compile`` traces: :mod:`._cache`)."""
    def build(m):
        fi = m.face_edges[:, [2, 0, 1]].t().contiguous()  # rows ab, bc, ac
        E = int(m.edges.shape[0])
        if fi.device.type == "meta":  # a meta mesh has no values: tables of the right shapes only
            return fi, fi.new_empty(E + 1, dtype=torch.int32), fi.new_empty(fi.numel(), dtype=torch.int32)
        by_code = fi.t().reshape(-1)  # position 3 f + slot -> edge
        order = torch.sort(by_code, stable=True).indices  # codes grouped by edge, increasing
        ptr = torch.zeros(E + 1, dtype=torch.int64, device=fi.device)
        ptr[1:] = torch.cumsum(torch.bincount(by_code, minlength=E), 0)
        return fi, ptr.to(torch.int32), order.to(torch.int32)

    tables = _require(mesh, "ops.face_curvature_tables", build)
    dev = torch.device(device)
    if tables[0].device == dev:
        return tables
    return _require(mesh, f"ops.face_curvature_tables.{dev}", lambda m: tuple(t.to(dev) for t in tables))


def _face_index(mesh, device) -> torch.Tensor:
    """``(3, F)`` canonical edges ``ab, bc, ac`` of the sorted faces (cached per mesh)."""
    return _tables(mesh, device)[0]


def face_curvature(edge_rot: torch.Tensor, mesh, cut=-1, kind: str = "two_prong") -> torch.Tensor | None:
    """Curvature of every sorted face ``[a<b<c]`` of a tet mesh: ``(*B, F, n, n)`` (Sec. 3.2, (3.2.1)).

    ``edge_rot (*B, E, n, n)``: one rotation per mesh edge in ``mesh.edges`` order, with any
    leading batch dimensions. Same values as the generic loop formula of
    :func:`torchconn.dec.curvature.face_curvature` on a ``TetMesh`` (loop ``a -> b -> c``,
    evaluation ``a``), written out for the triangle:

    * cut ``c`` (``-1`` or ``2``): ``R_ab R_bc - R_ac``;
    * cut ``b`` (``1`` or ``-2``): ``R_ab - R_ac R_bcᵀ``;
    * holonomy (``kind="holonomy"``, or cut ``0`` / ``-3``): ``R_ab R_bc R_acᵀ - I``.

    For ``n = 3`` the op ``torchconn::face_curvature`` (module doc); other ranks use batched
    matrix products. ``None`` for a mesh without sorted triangles or a ``cut`` that is not an
    integer in ``[-3, 2]`` (two-prong). ``edge_rot`` with another number of rows than
    ``mesh.edges`` raises ``ValueError`` naming both shapes.
    """
    if not _sorted_triangles(mesh) or not (kind == "holonomy" or (type(cut) is int and -3 <= cut <= 2)):
        return None
    E = int(mesh.edges.shape[0])
    if edge_rot.dim() < 3 or edge_rot.shape[-3] != E or edge_rot.shape[-1] != edge_rot.shape[-2]:
        short = f" (mesh edge index {E - 1} out of range)" if edge_rot.dim() >= 3 and edge_rot.shape[-3] < E else ""
        raise ValueError(f"face_curvature: edge_rot must have shape ({E}, n, n) (after optional leading batch "
                         f"dims), one rotation per mesh edge in mesh.edges order, got {tuple(edge_rot.shape)}{short}")
    c = cut % 3 if kind == "two_prong" else 0
    if edge_rot.shape[-1] == 3:
        fi, ptr, inc = _tables(mesh, edge_rot.device)
        if torch.compiler.is_compiling():
            return _face_curvature(edge_rot, fi, ptr, inc, c)
        return _CurvatureFn.apply(edge_rot, fi, ptr, inc, c)
    fe = mesh.face_edges.to(edge_rot.device)[:, [2, 0, 1]]
    F, n = fe.shape[0], edge_rot.shape[-1]
    F3 = edge_rot.index_select(-3, fe.reshape(-1)).unflatten(-3, (F, 3))
    Rab, Rbc, Rac = F3.unbind(-3)
    if c == 2:
        return Rab @ Rbc - Rac
    if c == 1:
        return Rab - Rac @ Rbc.transpose(-1, -2)
    eye = torch.eye(n, dtype=edge_rot.dtype, device=edge_rot.device)
    return (Rab @ Rbc) @ Rac.transpose(-1, -2) - eye
