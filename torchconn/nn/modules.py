"""``nn.Module`` wrappers of the operators, for pipelines (STYLE: functional core, thin modules).

Each module is built once from a mesh; the mesh's integer topology (and its vertex positions)
are registered as *buffers*, so ``module.to(device)`` / ``module.double()`` move them and the
forward pass never recomputes topology. Given a :class:`MeshBuffers` instead of a mesh, a module
shares it (several modules on one mesh then hold one copy of its topology, and the per-mesh
kernel tables are built once for all of them). ``forward`` takes the connection as

* a :class:`~torchconn.dec.connection.Connection` (its ``edge_rot`` is used),
* a :class:`~torchconn.nn.ConnectionField` (called to get the connection — gradients
  flow to its skew parameters), or
* a plain ``(E, n, n)`` tensor of edge rotations ``R_ij`` of the canonical edges ``(i<j)``.

Leading batch dims: every module accepts ``(*batch, E, n, n)`` rotations (a batched
``Connection`` or ``ConnectionField(..., batch_shape=...)``, or a tensor), a batch of
connections on the one mesh, and returns ``(*batch, F, n, n)``, ``(*batch, F, n)``,
``(*batch, T, n)``; ``frames`` may be ``(V, n, n)`` (shared) or ``(*batch, V, n, n)``.
:class:`BianchiCheck` checks every item.

Meta device: the modules can be built from a mesh moved with ``mesh.to("meta")`` and called
on ``meta`` tensors (shapes only, e.g. to size a pipeline); :class:`BianchiCheck` needs values
and raises ``ValueError`` there.

All modules compute exactly what the functional operators compute (they call them):

* :class:`Curvature` -- ``(*batch, F, n, n)`` per face, two-prong or holonomy (Sec. 3.2, (3.2.1));
* :class:`Torsion` -- ``(*batch, F, 3)`` per face, √R or naive (Def. 3.2);
* :class:`AveragedCovariantD` -- ``(*batch, T, 3)``, ``𝔡∇ Alt 𝔡∇ Alt θ̃`` per tet (Def. 5.2, end of Ch. 5);
* :class:`CovariantD` -- ``(*batch, T, 3)``, ``d∇d∇θ`` with variant averaged / behs21 / wedge (Ch. 4,
  Defs. 5.1-5.2);
* :class:`BianchiCheck` -- dict of max residuals; raises ``BianchiError`` (Sec. 2.4, 3.6, Ch. 5).

:meth:`Curvature.sqnorm` and :meth:`CovariantD.sqnorm` give a loss's weighted sum of squares
``(*batch,)`` directly, its gradient computed in the same fused sweep (no per-cell tensor).

Inputs (checked at ``forward``, reading no data, so no device sync):

* the connection must give a floating ``(*batch, E, n, n)`` tensor with ``E`` the mesh's edge
  count (``TypeError`` for a NumPy array or an integer tensor, ``ValueError`` naming the expected
  shape, with the batch dims of the input, and the given shape); :class:`Torsion`, :class:`CovariantD` and :class:`BianchiCheck` need ``n = 3``
  (the solder form lives in R^3), :class:`Curvature` takes any rank;
* ``frames`` must be ``None`` or a floating ``(V, n, n)`` or ``(*batch, V, n, n)`` tensor;
* dtypes: the result has the dtype (and device) of the edge rotations. The mesh's vertex
  positions and ``frames`` are cast to it, so a float32 connection on a float64 mesh (or
  with float64 frames) computes in float32: the connection is the variable, the mesh is data.
* values are not validated: NaN/inf rotations give NaN in the faces/tets that use them and
  nowhere else (a math op propagates NaN; check rotations explicitly with
  ``Connection.check_rotations``), except :class:`BianchiCheck`, a diagnostic that syncs
  anyway, which raises ``BianchiError`` naming the NaN term (``differential`` or
  ``algebraic``) and the tets.
"""
from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ..dec import bianchi as _bianchi
from ..dec import curvature as _curvature
from ..dec import dnabla as _dnabla
from ..dec import torsion as _torsion
from ..mesh import CellComplex, FaceGroup, TetMesh
from ..mesh.cells import face_groups_from_buffers
from ..ops.curvature_sqnorm import face_curvature_sqnorm as _face_curvature_sqnorm
from ..ops.tet_sqnorm import tet_dd_frames_sqnorm as _tet_dd_frames_sqnorm

__all__ = [
    "edge_rotations",
    "MeshBuffers",
    "Curvature",
    "Torsion",
    "AveragedCovariantD",
    "CovariantD",
    "BianchiCheck",
]

def edge_rotations(connection: Any, who: str = "edge_rotations") -> torch.Tensor:
    """``(*batch, E, n, n)`` edge rotations of a ``Connection``, ``ConnectionField`` or tensor.

    Raises ``TypeError`` (anything else, e.g. a NumPy array; a non-floating tensor) or
    ``ValueError`` (not ``(..., E, n, n)``), each message starting with ``who``. Reads no data.
    """
    if isinstance(connection, nn.Module):
        connection = connection()
    R = connection if isinstance(connection, torch.Tensor) else getattr(connection, "edge_rot", None)
    if not isinstance(R, torch.Tensor):
        raise TypeError(
            f"{who}: expected a Connection, a ConnectionField or an (..., E, n, n) tensor, got "
            f"{type(connection).__name__}; convert an array first, e.g. torch.as_tensor(R, dtype=torch.float64)"
        )
    if not R.is_floating_point():
        raise TypeError(f"{who}: edge rotations must be a floating-point tensor, got dtype {R.dtype}; "
                        f"pass e.g. R.to(torch.float64)")
    if R.ndim < 3 or R.shape[-1] != R.shape[-2]:
        raise ValueError(f"{who}: edge rotations must have shape (..., E, n, n) (optional leading batch "
                         f"dims), got {tuple(R.shape)}")
    return R


class MeshBuffers(nn.Module):
    """The topology (and vertex positions) of a ``TetMesh`` or ``CellComplex`` as module buffers.

    Every tensor the mesh owns (:meth:`torchconn.mesh.MeshBase.buffers`: integer topology and
    float geometry) is registered under its mesh attribute name, so the module duck-types as
    the mesh for the functional operators (``vertices``, ``edges``, ``faces``, ``face_edges``,
    ``tet_edges``, ... of a tet mesh; ``vertices``, ``edges``, ``face_groups`` of a cell
    complex; ``kind`` as the mesh's) and follows ``.to(device/dtype)`` of any parent module.
    Nothing is recomputed.

    Raises:
        TypeError: ``mesh`` is neither a :class:`TetMesh` nor a :class:`CellComplex`.
    """

    def __init__(self, mesh: Any):
        super().__init__()
        if not isinstance(mesh, (TetMesh, CellComplex)):
            raise TypeError(f"MeshBuffers needs a TetMesh or a CellComplex, got {type(mesh).__name__}")
        self.kind = mesh.kind
        for name, t in mesh.buffers().items():
            self.register_buffer(name, t.clone())

    @classmethod
    def of(cls, mesh: Any) -> "MeshBuffers":
        """``mesh`` itself when it is a ``MeshBuffers`` (shared: modules built on it hold one copy
        of the topology and one set of kernel tables), else ``MeshBuffers(mesh)``."""
        return mesh if isinstance(mesh, cls) else cls(mesh)

    @property
    def face_groups(self) -> dict[int, FaceGroup]:
        """Face groups of a cell complex rebuilt from the buffers (no copy)."""
        if self.kind != CellComplex.kind:
            raise AttributeError("face_groups exists only for a CellComplex")
        return face_groups_from_buffers(dict(self.named_buffers(recurse=False)))

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.edges.shape[0])

    def extra_repr(self) -> str:
        return f"kind={self.kind}, V={self.n_vertices}, E={self.n_edges}"


def _is_tet_mesh(mesh: Any) -> bool:
    """A ``TetMesh`` or the :class:`MeshBuffers` of one."""
    return isinstance(mesh, TetMesh) or (isinstance(mesh, MeshBuffers) and mesh.kind == TetMesh.kind)


def _rotations(connection: Any, mesh: MeshBuffers, who: str, n3: bool = False) -> torch.Tensor:
    """Edge rotations of ``connection`` checked against ``mesh`` (one per edge; ``n = 3`` if ``n3``)."""
    R = edge_rotations(connection, who)
    b = "".join(f"{x}, " for x in R.shape[:-3])
    if R.shape[-3] != mesh.n_edges:
        n = R.shape[-1]
        raise ValueError(
            f"{who}: got {R.shape[-3]} edge rotations per connection (shape {tuple(R.shape)}) for a mesh "
            f"with {mesh.n_edges} edges; pass one rotation R_ij per mesh edge, shape ({b}{mesh.n_edges}, "
            f"{n}, {n}) (leading batch dims {tuple(R.shape[:-3])}), in mesh.edges order"
        )
    if n3 and R.shape[-1] != 3:
        raise ValueError(
            f"{who}: the solder form lives in R^3, so the connection must have rank n = 3, i.e. edge "
            f"rotations of shape ({b}{mesh.n_edges}, 3, 3); got {tuple(R.shape)}"
        )
    return R


def _frames(frames: Any, R: torch.Tensor, mesh: MeshBuffers, who: str) -> torch.Tensor | None:
    """``frames (V, n, n)`` or ``(*batch, V, n, n)`` checked and cast to the dtype and device of
    the rotations ``R (*batch, E, n, n)``."""
    if frames is None:
        return None
    if not isinstance(frames, torch.Tensor) or not frames.is_floating_point():
        got = f"dtype {frames.dtype}" if isinstance(frames, torch.Tensor) else type(frames).__name__
        raise TypeError(f"{who}: frames must be None or a floating-point tensor, got {got}; convert it "
                        f"first, e.g. torch.as_tensor(frames, dtype=torch.float64)")
    n, V = R.shape[-1], mesh.n_vertices
    batch = tuple(R.shape[:-3])
    if tuple(frames.shape) not in ((V, n, n), (*batch, V, n, n)):
        alt = f" or {(*batch, V, n, n)} (one field per batch item)" if batch else ""
        raise ValueError(f"{who}: frames must have shape {(V, n, n)} (one frame per mesh vertex, rank of "
                         f"the connection){alt}, got {tuple(frames.shape)}")
    return frames.to(dtype=R.dtype, device=R.device)


def _weight(weight: Any, R: torch.Tensor, n: int, what: str, who: str) -> torch.Tensor | None:
    """Per-cell weights ``(n,)`` or ``(*batch, n)`` of :meth:`Curvature.sqnorm` /
    :meth:`CovariantD.sqnorm`, checked and cast to the dtype and device of ``R (*batch, E, 3, 3)``."""
    if weight is None:
        return None
    if not isinstance(weight, torch.Tensor) or not weight.is_floating_point():
        got = f"dtype {weight.dtype}" if isinstance(weight, torch.Tensor) else type(weight).__name__
        raise TypeError(f"{who}.sqnorm: weight must be None or a floating-point tensor, got {got}")
    batch = tuple(R.shape[:-3])
    if tuple(weight.shape) not in ((n,), (*batch, n)):
        alt = f" or {(*batch, n)}" if batch else ""
        raise ValueError(f"{who}.sqnorm: weight must have shape {(n,)} (one per {what}){alt}, got {tuple(weight.shape)}")
    return weight.to(dtype=R.dtype, device=R.device)


class Curvature(nn.Module):
    """Per-face discrete curvature of a connection (report Sec. 3.2; docs/conventions.md §1).

    Args:
        mesh: ``TetMesh`` (sorted faces ``[a<b<c]``, loop ``a -> b -> c``) or ``CellComplex``.
        kind: ``"two_prong"`` (default; ``⟨Ω,f⟩_{x0}^{xc}``) or ``"holonomy"`` ((3.2.1)).
        cut: cut position in each loop (default ``-1``: last vertex, so a tet-mesh face gives
            ``⟨Ω,[abc]⟩_a^c = R_ab R_bc − R_ac``).

    Forward: connection ``(*batch, E, n, n)`` → ``(*batch, F, n, n)`` in global face order, mapping the cut fiber to the
    evaluation fiber (first loop vertex).
    """

    def __init__(self, mesh: Any, kind: str = "two_prong", cut: int = -1):
        super().__init__()
        if kind not in ("two_prong", "holonomy"):
            raise ValueError(f"Curvature: kind must be 'two_prong' or 'holonomy', got {kind!r}")
        self.mesh = MeshBuffers.of(mesh)
        self.kind, self.cut = kind, cut

    def forward(self, connection: Any) -> torch.Tensor:
        """Curvature of every face.

        Args:
            connection: a ``Connection``, a ``ConnectionField`` or a tensor of edge rotations
                ``(*batch, E, n, n)`` (any rank ``n``), ``R_ij`` of the canonical edges ``i<j``.

        Returns:
            ``(*batch, F, n, n)``, dtype and device of the rotations, faces in the mesh's global
            face order: ``kind="two_prong"`` maps the cut fiber to the evaluation fiber (first
            loop vertex; on a tet mesh ``R_ab R_bc − R_ac``), ``kind="holonomy"`` gives the loop
            product minus the identity.
        """
        R = _rotations(connection, self.mesh, "Curvature")
        return _curvature.face_curvature(R, self.mesh, cut=self.cut, kind=self.kind)

    def sqnorm(self, connection: Any, weight: torch.Tensor | None = None) -> torch.Tensor:
        """``Σ_f w_f |C_f|_F²`` per batch item, ``C = self(connection)``: ``(*batch,)``.

        The value and gradient of a curvature loss without the ``(*batch, F, n, n)`` tensor: on a
        tet mesh with ``n = 3`` the op ``torchconn::face_curvature_sqnorm``
        (:mod:`torchconn.ops.curvature_sqnorm`: a C pass over the faces and the race-free one over
        the edges give the value and ``∂/∂R`` in the forward; same values and gradients as the reduction of :meth:`forward` to round-off,
        differentiable to any order, under every ``torch.func`` transform and ``torch.compile``);
        elsewhere :meth:`forward` reduced in torch.

        Args:
            connection: as :meth:`forward`.
            weight: ``None`` (1) or per-face weights ``(F,)`` / ``(*batch, F)``, global face order.
        """
        R = _rotations(connection, self.mesh, "Curvature")
        if _is_tet_mesh(self.mesh):
            w = _weight(weight, R, self.mesh.faces.shape[0], "face", "Curvature")
            out = _face_curvature_sqnorm(R, self.mesh, w, cut=self.cut, kind=self.kind)
            if out is not None:
                return out
        per = _curvature.face_curvature(R, self.mesh, cut=self.cut, kind=self.kind).square().sum((-1, -2))
        w = _weight(weight, R, per.shape[-1], "face", "Curvature")
        return (per if w is None else w * per).sum(-1)


class Torsion(nn.Module):
    """Per-face discrete torsion of the solder form (report Def. 3.2; Sec. 3.3).

    Args:
        mesh: ``TetMesh`` or ``CellComplex`` (its vertex positions define the solder form).
        kind: ``"sqrt"`` (θ̃_ij = √R_ij θ_ij, convergent) or ``"naive"`` (plain θ, divergent).
        cut: cut position (default ``-1``: last loop vertex).

    Forward: ``(connection (*batch, E, 3, 3), frames=None)`` → ``(*batch, F, 3)`` in the fiber of each
    face's evaluation vertex; ``frames (V, 3, 3)`` reads the rotations in a frame field (same convention as
    :func:`torchconn.torsion.face_torsion` and :func:`torchconn.dnabla.tet_solder_sqrt`:
    computed with ``F_i R_ij F_jᵀ`` in the ambient frame, returned in ``F_{x0}``, exactly gauge
    covariant); ``None`` means the global coordinate frame.
    """

    def __init__(self, mesh: Any, kind: str = "sqrt", cut: int = -1):
        super().__init__()
        if kind not in ("sqrt", "naive"):
            raise ValueError(f"Torsion: kind must be 'sqrt' or 'naive', got {kind!r}")
        self.mesh = MeshBuffers.of(mesh)
        self.kind, self.cut = kind, cut

    def forward(self, connection: Any, frames: torch.Tensor | None = None) -> torch.Tensor:
        """Torsion of the solder form on every face.

        Args:
            connection: a ``Connection``, a ``ConnectionField`` or edge rotations
                ``(*batch, E, 3, 3)``.
            frames: ``None`` (the global coordinate frame) or a frame field ``(V, 3, 3)`` /
                ``(*batch, V, 3, 3)``, axes as columns.

        Returns:
            ``(*batch, F, 3)``, dtype and device of the rotations: per face, a vector in the
            fiber (frame) of its evaluation vertex.
        """
        R = _rotations(connection, self.mesh, "Torsion", n3=True)
        frames = _frames(frames, R, self.mesh, "Torsion")
        return _torsion.face_torsion(R, self.mesh, kind=self.kind, cut=self.cut, frames=frames)


class CovariantD(nn.Module):
    """Per-tet second covariant exterior derivative of the solder form, ``(*batch, T, 3)``.

    Args:
        mesh: ``TetMesh``.
        variant: ``"averaged"`` — ``𝔡∇ Alt 𝔡∇ Alt θ̃`` (Def. 5.2, convergent);
            ``"behs21"`` — BEHS21 twice on the plain θ, ``(R_ab R_bc − R_ac) θ_cd`` (Ch. 4,
            divergent); ``"wedge"`` — the explicit end-of-Ch. 5 discrete ``Ω∧θ``.

    Forward: ``(connection (*batch, E, 3, 3), frames=None)`` → ``(*batch, T, 3)`` in the fiber of
    ``tets[t, 0]``; divide by the tet volume to compare with the smooth ``Ω∧θ``.
    """

    _FUNCS = {
        "averaged": _dnabla.averaged_dd_solder,
        "behs21": _dnabla.behs21_dd_solder,
        "wedge": _dnabla.wedge_solder,
    }

    def __init__(self, mesh: Any, variant: str = "averaged"):
        super().__init__()
        if variant not in self._FUNCS:
            raise ValueError(f"CovariantD: variant must be one of {sorted(self._FUNCS)}, got {variant!r}")
        if not _is_tet_mesh(mesh):
            raise TypeError(f"CovariantD needs a TetMesh, got {type(mesh).__name__}")
        self.mesh = MeshBuffers.of(mesh)
        self.variant = variant

    def forward(self, connection: Any, frames: torch.Tensor | None = None) -> torch.Tensor:
        """The chosen ``d∇d∇θ`` on every tet.

        Args:
            connection: a ``Connection``, a ``ConnectionField`` or edge rotations
                ``(*batch, E, 3, 3)``.
            frames: ``None`` (the global coordinate frame) or a frame field ``(V, 3, 3)`` /
                ``(*batch, V, 3, 3)``, axes as columns.

        Returns:
            ``(*batch, T, 3)``, dtype and device of the rotations: per tet, a vector in the fiber
            of its first vertex ``tets[t, 0]``; divide by the tet volume to compare with the
            smooth ``Ω∧θ``.
        """
        who = type(self).__name__
        R = _rotations(connection, self.mesh, who, n3=True)
        return self._FUNCS[self.variant](R, self.mesh, _frames(frames, R, self.mesh, who))

    def sqnorm(self, connection: Any, frames: torch.Tensor | None = None,
               weight: torch.Tensor | None = None) -> torch.Tensor:
        """``Σ_t w_t |d∇d∇θ_t|²`` per batch item, ``d∇d∇θ = self(connection, frames)``: ``(*batch,)``.

        The value and gradient of a loss on it without the ``(*batch, T, 3)`` tensor: for the
        averaged variant the op ``torchconn::tet_dd_frames_sqnorm``
        (:mod:`torchconn.ops.tet_sqnorm`: one C sweep gives the value and the gradients in the
        rotations and the frames, tets with ``w_t = 0`` skipped; ``frames=None``: the global
        frame, no frame products; same values and gradients as the reduction of :meth:`forward` to
        round-off, differentiable to any order, under every ``torch.func`` transform and
        ``torch.compile``); the other variants reduce :meth:`forward` in torch.

        Args:
            connection, frames: as :meth:`forward`.
            weight: ``None`` (1) or per-tet weights ``(T,)`` / ``(*batch, T)``.
        """
        who = type(self).__name__
        R = _rotations(connection, self.mesh, who, n3=True)
        F = _frames(frames, R, self.mesh, who)
        T = self.mesh.tets.shape[0]
        w = _weight(weight, R, T, "tet", who)
        if self.variant == "averaged" and _is_tet_mesh(self.mesh):
            if F is not None:
                F = F.expand(*R.shape[:-3], *F.shape[-3:])
            return _tet_dd_frames_sqnorm(R, F, R.new_ones(T) if w is None else w, self.mesh)
        per = self._FUNCS[self.variant](R, self.mesh, F).square().sum(-1)
        return (per if w is None else w * per).sum(-1)


class AveragedCovariantD(CovariantD):
    """The averaged ``d∇d∇θ = 𝔡∇ Alt 𝔡∇ Alt θ̃`` per tet (Def. 5.2): ``CovariantD(mesh, "averaged")``.

    Args:
        mesh: ``TetMesh`` (or a ``TetMeshBatch`` of several meshes).

    Forward: ``(connection (*batch, E, 3, 3), frames=None)`` → ``(*batch, T, 3)``: per tet, a
    vector in the fiber of its first vertex ``tets[t, 0]``, of the dtype and device of the
    rotations (:meth:`CovariantD.forward`). Divide by the tet volume to compare with the smooth
    ``Ω∧θ``, to which it converges (the discrete algebraic Bianchi identity: it equals the
    explicit wedge ``CovariantD(mesh, "wedge")`` to round-off).
    """

    def __init__(self, mesh: Any):
        super().__init__(mesh, variant="averaged")


class BianchiCheck(nn.Module):
    """Invariant check: the exact discrete Bianchi identities on every tet.

    Forward: ``(connection, frames=None)`` → ``{"differential": max residual, "algebraic": max
    residual}`` (floats) — the differential identity ``⟨𝔡∇Ω,[abcd]⟩_a^d = 0`` with ``Ω = 𝔡∇w``
    and the algebraic one ``𝔡∇Alt𝔡∇Alt θ̃ − Ω∧θ = 0`` (explicit Ch. 5 wedge). Raises
    :class:`torchconn.bianchi.BianchiError` naming the worst tets when a residual exceeds
    ``atol`` (default: the dtype's ``identity`` tolerance) or is not finite — a structural bug
    or a NaN. A connection that is not orthogonal (or has ``det -1``) to its dtype's
    ``rotation`` tolerance raises ``ValueError`` naming the worst edge and the remedy,
    ``so3.project_to_rotation``, instead (the identities hold for rotations; e.g. float32
    rotations cast to float64 are orthogonal only to ~1e-7). The check runs on detached
    rotations (it is a diagnostic, not a loss term). With batch dims every item is checked and
    the maxima are over the whole batch. Needs values: ``ValueError`` on ``meta`` tensors.

    Transforms: it runs under autograd and inside ``torch.func.grad`` / ``jacrev`` / ``jacfwd``
    / ``jvp`` (on the primal values); inside ``torch.func.vmap`` it raises ``RuntimeError`` (a
    vmapped item has no Python value: call it on the whole batch); ``torch.compile`` runs it
    outside the graph (``torch.compiler.disable``), so ``fullgraph=True`` raises
    ``torch._dynamo.exc.Unsupported`` quoting that reason: call it outside the compiled function.
    """

    def __init__(self, mesh: Any, atol: float | None = None):
        super().__init__()
        if not _is_tet_mesh(mesh):
            raise TypeError(f"BianchiCheck needs a TetMesh, got {type(mesh).__name__}")
        self.mesh = MeshBuffers.of(mesh)
        self.atol = atol

    @torch.compiler.disable(reason=_bianchi._compile_reason("BianchiCheck"))
    @torch.no_grad()
    def forward(self, connection: Any, frames: torch.Tensor | None = None) -> dict[str, float]:
        """Check both identities on every tet (and every batch item).

        Args:
            connection: a ``Connection``, a ``ConnectionField`` or edge rotations
                ``(*batch, E, 3, 3)``.
            frames: ``None`` or a frame field ``(V, 3, 3)`` / ``(*batch, V, 3, 3)``.

        Returns:
            ``{"differential": float, "algebraic": float}``, the maximum residuals.

        Raises:
            BianchiError: a residual above ``atol`` or not finite.
            ValueError: the rotations are not orthogonal to their dtype's tolerance, or are on
                ``meta``.
        """
        R = _rotations(connection, self.mesh, "BianchiCheck", n3=True).detach()
        return _bianchi.run_check("BianchiCheck", R, self.mesh, atol=self.atol,
                                  frames=_frames(frames, R, self.mesh, "BianchiCheck"))
