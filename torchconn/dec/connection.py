"""Discrete metric connections: one rotation per canonical edge (report Sec. 3.1).

Conventions (docs/conventions.md §1)
------------------------------------
* ``edges (E, 2)`` are canonical: ``edges[e] = (i, j)`` with ``i < j``, unique rows.
* ``edge_rot[e] = R_ij ∈ SO(n)`` maps the coordinates of a vector at ``v_j`` (frame ``F_j``) to
  the coordinates of its parallel transport at ``v_i`` (frame ``F_i``); ``R_ji = R_ijᵀ``.
* A path product ``T(p0, ..., pk) = R_{p0p1} ... R_{p(k-1)pk}`` maps the fiber at ``pk`` to the
  fiber at ``p0`` (:meth:`Connection.path`).
* Connection 1-form ``w_ij = R_ij - I`` (eq. 3.1.2), with ``R_ij w_ji = -w_ij``.
* Gauge (eq. 2.1.2; docs/conventions.md §1): new frames ``F'_i = F_i G_iᵀ`` change coordinates by
  ``x' = G_i x`` and the transports by ``R'_ij = G_i R_ij G_jᵀ``; applying ``G1`` then ``G2``
  equals applying ``G2 G1`` (:meth:`Connection.gauge`).
* Half transport ``√R_ij`` (report Sec. 3.3): principal square root, the transport from the
  edge midpoint to ``v_i``.

:class:`Connection` is a plain container of tensors (functional level); the ``nn.Module``
parametrization ``edge_rot = exp(hat(params))`` used for optimization is
:class:`torchconn.nn.ConnectionField`.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..lie import so3, son
from ..lie._validate import rotation_defects
from ..mesh.base import lookup_edges
from .transport import dense_simplex_transports, orient, pair_list, path_product
from ..tolerances import get_eps

__all__ = ["Connection"]

_MAX_LISTED = 10


def _list_some(items: list, total: int) -> str:
    more = f" (and {total - len(items)} more)" if total > len(items) else ""
    return f"{items}{more}"


def _as_edges(edges: Any, device=None) -> torch.Tensor:
    edges = torch.as_tensor(edges, device=device)
    if edges.dim() != 2 or edges.shape[1] != 2:
        raise ValueError(f"edges must have shape (E, 2), got {tuple(edges.shape)}")
    if edges.is_floating_point() or edges.is_complex() or edges.dtype == torch.bool:
        raise TypeError(f"edges must be an integer tensor, got dtype {edges.dtype}")
    return edges.to(torch.long)


def _raise_on_rows(edges: torch.Tensor, bad_mask: torch.Tensor, what: str) -> None:
    """Raise ``ValueError`` naming the first offending edge indices and rows where ``bad_mask``."""
    if bad_mask.device.type == "meta":  # no values to check (see _check_edges)
        return
    if bool(bad_mask.any()):
        bad = torch.nonzero(bad_mask).flatten()
        raise ValueError(
            f"{what} at edge indices {_list_some(bad[:_MAX_LISTED].tolist(), bad.numel())} "
            f"(rows {edges[bad[:_MAX_LISTED]].tolist()})"
        )


def _check_edges(edges: torch.Tensor, n_vertices: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate canonical edges; return ``(sorted_keys, perm)`` of keys ``i*V + j``.

    Raises ``ValueError`` naming the offending edge indices (out of range, not ``i < j``,
    duplicated). On ``meta`` tensors there are no values: the checks are skipped and only the
    shapes of the lookup are produced (validate the edges on a real device first).
    """
    E = edges.shape[0]
    V = int(n_vertices)
    if V < 0:
        raise ValueError(f"n_vertices must be >= 0, got {n_vertices}")
    i, j = edges[:, 0], edges[:, 1]
    _raise_on_rows(edges, (i < 0) | (j < 0) | (i >= V) | (j >= V), f"edges: vertex indices out of range [0, {V})")
    _raise_on_rows(edges, i >= j, "edges must be canonical (edges[e,0] < edges[e,1]); violated")
    keys = i * V + j
    sorted_keys, perm = torch.sort(keys, stable=True)
    if E > 1 and keys.device.type != "meta":
        dup = sorted_keys[1:] == sorted_keys[:-1]
        if bool(dup.any()):
            pos = torch.nonzero(dup).flatten()
            pairs = torch.stack((perm[pos], perm[pos + 1]), 1)
            raise ValueError(
                f"edges: duplicated rows at edge index pairs "
                f"{_list_some(pairs[:_MAX_LISTED].tolist(), pos.numel())}"
            )
    return sorted_keys, perm


def _identity(E: int, n: int, dtype, device, batch_shape=()) -> torch.Tensor:
    return torch.eye(n, dtype=dtype, device=device).expand(*batch_shape, E, n, n).clone()


def _exp_params(params: torch.Tensor, n: int) -> torch.Tensor:
    """``exp(hat(params))`` with the so3 closed form for ``n = 3``."""
    if n == 3:
        return so3.exp(params)
    return son.exp_params(params, n)


def _log_params(R: torch.Tensor) -> torch.Tensor:
    """Skew parameters of the principal log (inverse of :func:`_exp_params`)."""
    n = R.shape[-1]
    if n == 3:
        return so3.log(R)
    return son.vee(son.log(R))


class Connection:
    """A discrete connection ``∇ = {R_ij}``: one rotation per canonical edge (report eq. 3.1.1).

    Args:
        edge_rot: ``(*batch, E, n, n)`` rotations, ``edge_rot[..., e, :, :] = R_ij`` for
            ``edges[e] = (i, j)``, ``i < j``: maps the fiber at ``v_j`` to the fiber at ``v_i``.
            ``batch`` (:attr:`batch_shape`, may be empty) holds a batch of connections on the
            same edges, as roma / pytorch3d take leading batch dims: every operator of
            :mod:`torchconn.dec` and module of :mod:`torchconn.nn` returns its values with
            the same leading dims.
        edges: ``(E, 2)`` integer tensor of canonical edges (``i < j``, unique rows, any order).
        n_vertices: number of vertices ``V`` (indices in ``[0, V)``).
        validate: also check that every ``edge_rot[..., e, :, :]`` is a rotation (synchronizes).

    On the ``meta`` device (shapes only) the checks that need values (edge ranges, duplicates,
    ``validate``) are skipped; shapes are still checked.

    Raises:
        ValueError: bad shapes; edges out of range, not canonical or duplicated (the message
            names the edge indices); with ``validate``, non-rotation edges (edge indices and
            vertex pairs in the message).

    The edge lookup used by :meth:`transport` (sorted keys ``i*V + j`` and ``searchsorted``) is
    built once here and shared by every connection derived from this one (:meth:`gauge`,
    :meth:`half`, :meth:`detach`, ...). Rotations are differentiable tensors; edges are not.
    """

    def __init__(self, edge_rot: torch.Tensor, edges: Any, n_vertices: int, *, validate: bool = False):
        if not isinstance(edge_rot, torch.Tensor) or not edge_rot.is_floating_point():
            got = f"dtype {edge_rot.dtype}" if isinstance(edge_rot, torch.Tensor) else type(edge_rot).__name__
            raise TypeError(
                f"Connection: edge_rot must be a floating-point tensor of shape (..., E, n, n), got {got}; "
                f"convert it first, e.g. torch.as_tensor(edge_rot, dtype=torch.float64)"
            )
        if edge_rot.dim() < 3 or edge_rot.shape[-1] != edge_rot.shape[-2]:
            raise ValueError(f"edge_rot must have shape (..., E, n, n) (optional leading batch dims), "
                             f"got {tuple(edge_rot.shape)}")
        edges = _as_edges(edges, device=edge_rot.device)
        if edges.shape[0] != edge_rot.shape[-3]:
            batch = "".join(f"{b}, " for b in edge_rot.shape[:-3])
            raise ValueError(
                f"edge_rot has {edge_rot.shape[-3]} matrices but edges has {edges.shape[0]} rows: expected "
                f"shape ({batch}{edges.shape[0]}, {edge_rot.shape[-1]}, {edge_rot.shape[-1]}) (one matrix per "
                f"edge after the leading batch dims {tuple(edge_rot.shape[:-3])}), got {tuple(edge_rot.shape)}"
            )
        self.edge_rot = edge_rot
        self.edges = edges
        self.n_vertices = int(n_vertices)
        self._lookup = _check_edges(edges, self.n_vertices)
        if validate:
            self.check_rotations()

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def _trusted(cls, edge_rot, edges, n_vertices, lookup=None) -> "Connection":
        """Build without validating the (already validated) edges; shares ``lookup``."""
        self = cls.__new__(cls)
        self.edge_rot = edge_rot
        self.edges = edges
        self.n_vertices = int(n_vertices)
        self._lookup = lookup
        return self

    def _replace(self, edge_rot: torch.Tensor) -> "Connection":
        lookup = self._lookup
        if lookup is not None and lookup[0].device != edge_rot.device:
            lookup = None
        edges = self.edges.to(edge_rot.device)
        return Connection._trusted(edge_rot, edges, self.n_vertices, lookup)

    def _get_lookup(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self._lookup is None:
            keys = self.edges[:, 0] * self.n_vertices + self.edges[:, 1]
            self._lookup = torch.sort(keys, stable=True)
        return self._lookup

    # ------------------------------------------------------------------ properties
    @property
    def n(self) -> int:
        """Rank of the bundle (fiber dimension)."""
        return self.edge_rot.shape[-1]

    @property
    def n_edges(self) -> int:
        return self.edge_rot.shape[-3]

    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch dims of ``edge_rot`` (``torch.Size([])`` for a single connection)."""
        return self.edge_rot.shape[:-3]

    @property
    def dtype(self) -> torch.dtype:
        return self.edge_rot.dtype

    @property
    def device(self) -> torch.device:
        return self.edge_rot.device

    def __repr__(self) -> str:
        b = f"batch_shape={tuple(self.batch_shape)}, " if len(self.batch_shape) else ""
        return (
            f"Connection({b}n={self.n}, n_vertices={self.n_vertices}, n_edges={self.n_edges}, "
            f"dtype={self.dtype}, device={self.device})"
        )

    # ------------------------------------------------------------------ validation
    def check_rotations(self, atol: float | None = None, *, name: str = "edge_rot") -> None:
        """Raise ``ValueError`` unless every ``edge_rot[e]`` is a rotation.

        Tolerance ``atol`` on ``||Rᵀ R - I||_F`` defaults to ``get_eps("rotation", dtype)``. The
        message starts with ``name``, lists the offending edge indices and their vertex pairs,
        then each defect found with its edge indices: ``non-finite entries (NaN/inf)``, ``not
        orthogonal`` (with the value of ``||Rᵀ R - I||_F`` at the first one) and ``det -1 (a
        reflection)``; and says what to do. Synchronizes (explicit validation; not called by
        the operators). With batch dims an edge is reported when its matrix is bad in at least
        one batch item (the largest defect / smallest determinant over the batch is shown).
        Skipped on the ``meta`` device (no values).
        """
        if self.edge_rot.device.type == "meta":
            return
        if atol is None:
            atol = get_eps("rotation", self.dtype)
        with torch.no_grad():
            bad_fin, bad_orth, bad_det, err, det = rotation_defects(self.edge_rot, atol)
            if len(self.batch_shape):  # reduce over the batch: per edge
                E = self.n_edges
                bad_fin, bad_orth, bad_det = (m.reshape(-1, E).any(0) for m in (bad_fin, bad_orth, bad_det))
                err, det = err.reshape(-1, E).amax(0), det.reshape(-1, E).amin(0)
            bad = bad_fin | bad_orth | bad_det
            if not bool(bad.any()):
                return
            idx = torch.nonzero(bad).flatten()
            shown = idx[:_MAX_LISTED]
            parts = []
            for mask, label in ((bad_fin, "non-finite entries (NaN/inf)"), (bad_orth, "not orthogonal"),
                                (bad_det, "det -1 (a reflection)")):
                e = torch.nonzero(mask).flatten()
                if e.numel() == 0:
                    continue
                first, value = int(e[0]), ""
                if mask is bad_orth:
                    value = f" (||R^T R - I||_F = {float(err[first]):.3e} > atol {atol:.1e} at edge {first})"
                elif mask is bad_det:
                    value = f" (det = {float(det[first]):.6f} at edge {first})"
                parts.append(f"{label} at edge indices {_list_some(e[:_MAX_LISTED].tolist(), e.numel())}{value}")
            where = f" (in at least one item of the batch {tuple(self.batch_shape)})" if len(self.batch_shape) else ""
            raise ValueError(
                f"{name}: {idx.numel()} of {self.n_edges} edge matrices{where} are not rotations, at edge "
                f"indices {_list_some(shown.tolist(), idx.numel())} (vertex pairs "
                f"{self.edges[shown].tolist()}): " + "; ".join(parts) + ". Pass rotations "
                "(orthogonal, det +1), e.g. project them with so3.project_to_rotation"
            )

    # ------------------------------------------------------------------ lookups and transports
    def edge_index(self, i: Any, j: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Edge index and orientation sign of vertex pairs.

        Args:
            i, j: integer tensors (broadcastable, any shape ``S``) of vertex indices.

        Returns:
            ``(edge_idx, edge_sign)``, both of shape ``S``: ``edges[edge_idx] == (i, j)`` with
            sign ``+1`` where ``i < j``, ``== (j, i)`` with sign ``-1`` otherwise.

        Raises:
            TypeError: non-integer indices.
            MeshError: naming the pairs ``(i, j)`` that are not edges (including ``i == j``
                and out-of-range vertices).

        The lookup of :func:`torchconn.mesh.base.lookup_edges` (``searchsorted`` on keys
        ``min*V + max``): it checks every pair and therefore synchronizes with the device;
        operators on meshes should use precomputed ``(edge_idx, edge_sign)`` buffers with
        :meth:`oriented` instead.
        """
        sorted_keys, perm = self._get_lookup()
        return lookup_edges(sorted_keys, self.n_vertices, i, j, perm=perm, owner="connection")

    def transport(self, i: Any, j: Any) -> torch.Tensor:
        """``R_ij`` for batches of vertex pairs: ``i, j (S)`` -> ``(*batch_shape, S, n, n)``.

        Fiber at ``v_j`` -> fiber at ``v_i``: ``edge_rot[e]`` for a canonical pair, its transpose
        for ``i > j``. Raises :class:`~torchconn.mesh.MeshError` naming the pairs that are not edges.
        """
        idx, sign = self.edge_index(i, j)
        return orient(self.edge_rot, idx, sign)

    def path(self, vertices: Any) -> torch.Tensor:
        """Path product ``T(p0..pk) = R_{p0p1} ... R_{p(k-1)pk}`` (docs/conventions.md §1).

        Args:
            vertices: ``(..., k+1)`` integer vertex sequences; consecutive vertices must be edges.

        Returns:
            ``(*batch_shape, ..., n, n)``, mapping the fiber at ``pk`` to the fiber at ``p0``
            (identity for ``k = 0``). A closed path ``[p0, ..., p0]`` gives the holonomy at ``p0`` (eq. 3.2.1
            plus ``I``).
        """
        v = torch.as_tensor(vertices, device=self.edges.device)
        if v.dim() < 1 or v.shape[-1] < 1:
            raise ValueError(f"path expects vertices of shape (..., k+1), k >= 0, got {tuple(v.shape)}")
        if v.shape[-1] == 1:
            eye = torch.eye(self.n, dtype=self.dtype, device=self.device)
            return eye.expand(*self.batch_shape, *v.shape[:-1], self.n, self.n).clone()
        return path_product(self.transport(v[..., :-1], v[..., 1:]), dim=-3)

    def oriented(self, edge_idx: torch.Tensor, edge_sign: torch.Tensor) -> torch.Tensor:
        """Oriented transports ``(...)`` -> ``(..., n, n)`` (:func:`transport.orient`)."""
        return orient(self.edge_rot, edge_idx, edge_sign)

    def simplex_transports(
        self, simplex_edges: torch.Tensor, simplex_edge_signs: torch.Tensor, s: int
    ) -> torch.Tensor:
        """Dense per-simplex transport table.

        Args:
            simplex_edges: ``(N, P)`` edge indices in :func:`transport.pair_list` order
                (``P = s(s-1)/2``), e.g. ``mesh.tet_edges`` with ``s = 4``.
            simplex_edge_signs: ``(N, P)`` orientation signs (``+1``: local pair ``(x_a, x_b)``,
                ``a < b``, is the stored orientation).
            s: vertices per simplex.

        Returns:
            ``(*batch_shape, N, s, s, n, n)`` with ``[..., t, a, b, :, :] = R_{x_a x_b}`` (fiber at ``x_b`` -> ``x_a``),
            identity on the diagonal.
        """
        P = len(pair_list(s))
        if simplex_edges.shape[-1] != P or simplex_edge_signs.shape != simplex_edges.shape:
            raise ValueError(
                f"simplex_edges/simplex_edge_signs must both have shape (N, {P}) for s={s}, got "
                f"{tuple(simplex_edges.shape)} and {tuple(simplex_edge_signs.shape)}"
            )
        return dense_simplex_transports(self.oriented(simplex_edges, simplex_edge_signs), s)

    # ------------------------------------------------------------------ derived connections
    def one_form(self) -> torch.Tensor:
        """Discrete connection 1-form ``w_ij = R_ij - I`` per canonical edge (eq. 3.1.2) -> ``(*batch_shape, E, n, n)``."""
        return self.edge_rot - torch.eye(self.n, dtype=self.dtype, device=self.device)

    def gauge(self, G: torch.Tensor, *, validate: bool = False) -> "Connection":
        """Gauge transform ``R'_ij = G_i R_ij G_jᵀ`` (eq. 2.1.2; docs/conventions.md §1).

        Args:
            G: ``(V, n, n)`` rotations, ``G_i`` the change of coordinates ``x' = G_i x`` at ``v_i``;
                or ``(*batch, V, n, n)``, one gauge per item, with ``batch`` broadcasting against
                :attr:`batch_shape` (the result has the broadcast batch).
            validate: check that ``G`` holds rotations.

        ``c.gauge(G1).gauge(G2) == c.gauge(G2 @ G1)``; ``c.gauge(I) == c``. Differentiable in
        both ``edge_rot`` and ``G``.
        """
        if G.dim() < 3 or tuple(G.shape[-3:]) != (self.n_vertices, self.n, self.n):
            raise ValueError(
                f"gauge expects G of shape ({self.n_vertices}, {self.n}, {self.n}) or (..., {self.n_vertices}, "
                f"{self.n}, {self.n}) (leading batch dims), got {tuple(G.shape)}"
            )
        if validate:
            son.check_rotation(G, name="gauge G")
        e = self.edges.to(G.device)
        R = G.index_select(-3, e[:, 0]) @ self.edge_rot.to(G.device) @ G.index_select(-3, e[:, 1]).transpose(-1, -2)
        return self._replace(R)

    def half(self) -> "Connection":
        """Half transports ``√R_ij = exp(½ log R_ij)`` per edge (report Sec. 3.3; docs/conventions.md §1).

        Edge midpoint -> ``v_i``. Uses :func:`so3.sqrt` for ``n = 3`` and
        ``son.sqrt`` otherwise (principal branch: angles ``< pi``).
        """
        if self.n == 3:
            return self._replace(so3.sqrt(self.edge_rot))
        return self._replace(son.sqrt(self.edge_rot))

    def to(self, *args, **kwargs) -> "Connection":
        """Move/cast ``edge_rot`` like :meth:`torch.Tensor.to`; edges follow the device."""
        return self._replace(self.edge_rot.to(*args, **kwargs))

    def detach(self) -> "Connection":
        return self._replace(self.edge_rot.detach())

    # ------------------------------------------------------------------ constructors
    @classmethod
    def identity(
        cls, edges: Any, n_vertices: int, n: int = 3, dtype: torch.dtype | None = None, device=None,
        batch_shape=(),
    ) -> "Connection":
        """The trivial connection ``R_ij = I`` (flat, zero torsion of the identity frames);
        ``edge_rot`` of shape ``(*batch_shape, E, n, n)``."""
        edges = _as_edges(edges, device=device)
        dtype = dtype or torch.get_default_dtype()
        return cls(_identity(edges.shape[0], n, dtype, edges.device, tuple(batch_shape)), edges, n_vertices)

    @classmethod
    def random(
        cls,
        edges: Any,
        n_vertices: int,
        n: int = 3,
        generator: torch.Generator | None = None,
        scale: float | None = None,
        dtype: torch.dtype | None = None,
        device=None,
        batch_shape=(),
    ) -> "Connection":
        """A random connection, ``edge_rot`` of shape ``(*batch_shape, E, n, n)``.

        ``scale=None``: independent Haar-uniform rotations per edge. Otherwise
        ``R_ij = exp(hat(scale * ξ))`` with ``ξ`` standard Gaussian skew parameters
        (``so(n)`` of dimension ``n(n-1)/2``), i.e. rotations near the identity for small scale.
        All randomness goes through ``generator``.
        """
        edges = _as_edges(edges, device=device)
        dtype = dtype or torch.get_default_dtype()
        batch_shape = tuple(batch_shape)
        E = edges.shape[0]
        N = E * int(np.prod(batch_shape, dtype=np.int64))
        dev = edges.device
        if scale is None:
            if n == 3:
                R = so3.random_rotation(N, generator=generator, dtype=dtype, device=dev)
            else:
                R = son.random_rotation(N, n=n, generator=generator, dtype=dtype, device=dev)
        else:
            xi = torch.randn(N, son.dim(n), generator=generator, dtype=dtype, device=dev)
            R = _exp_params(scale * xi, n)
        R = R.reshape(*batch_shape, E, n, n)
        return cls(R, edges, n_vertices)

    @classmethod
    def from_smooth(
        cls,
        vertices: torch.Tensor,
        edges: Any,
        smooth,
        method: str = "midpoint",
        steps: int = 512,
        n_vertices: int | None = None,
    ) -> "Connection":
        """Discretize a smooth connection (:class:`torchconn.smooth.SmoothConnection`).

        ``R_ij`` = transport of the straight segment ``v_i -> v_j`` (fiber at ``v_j`` -> ``v_i``):
        ``"midpoint"`` = ``exp(ω_m[v_j - v_i])`` (report Sec. 3.4, the main series) or
        ``"path_ordered"`` (docs/conventions.md §1, ``steps`` Magnus sub-steps).

        Args:
            vertices: ``(V, 3)`` positions (their dtype/device are used).
            edges: ``(E, 2)`` canonical edges.
            smooth: object with ``transport(a, b, method=..., steps=...)``.
            n_vertices: defaults to ``vertices.shape[0]``.
        """
        edges = _as_edges(edges, device=vertices.device)
        V = vertices.shape[0] if n_vertices is None else n_vertices
        lookup = _check_edges(edges, V)  # validate before indexing
        R = smooth.transport(vertices[edges[:, 0]], vertices[edges[:, 1]], method=method, steps=steps)
        return cls._trusted(R, edges, V, lookup)

    @classmethod
    def from_frames(cls, frames: torch.Tensor, edges: Any) -> "Connection":
        """The flat connection of a frame field: ``R_ij = F_iᵀ F_j``.

        ``frames[i] = F_i (n, n)`` holds the frame vectors of vertex ``i`` as *columns*, in a
        common ambient basis. A vector with coordinates ``X`` in ``F_j`` is the ambient vector
        ``F_j X``; read in ``F_i`` it has coordinates ``F_iᵀ F_j X``, so ``R_ij`` maps the fiber
        at ``v_j`` to the fiber at ``v_i`` as required. Every closed path has trivial holonomy
        (``T(p0..p0) = I``); equivalently this is ``identity.gauge(G)`` with ``G_i = F_iᵀ``.
        ``frames (*batch, V, n, n)`` with leading batch dims gives a batched connection.
        """
        if frames.dim() < 3 or frames.shape[-1] != frames.shape[-2]:
            raise ValueError(f"frames must have shape (V, n, n) or (..., V, n, n), got {tuple(frames.shape)}")
        edges = _as_edges(edges, device=frames.device)
        V = frames.shape[-3]
        lookup = _check_edges(edges, V)
        R = frames.index_select(-3, edges[:, 0]).transpose(-1, -2) @ frames.index_select(-3, edges[:, 1])
        return cls._trusted(R, edges, V, lookup)

    @classmethod
    def from_mesh(cls, mesh, edge_rot: torch.Tensor | None = None, n: int = 3, *, validate: bool = False) -> "Connection":
        """Connection on ``mesh.edges`` / ``mesh.n_vertices`` (identity when ``edge_rot`` is None).

        Only reads ``mesh.edges``, ``mesh.n_vertices`` and (for dtype/device) ``mesh.vertices``.
        """
        if edge_rot is None:
            v = mesh.vertices
            return cls.identity(mesh.edges, mesh.n_vertices, n=n, dtype=v.dtype, device=v.device)
        return cls(edge_rot, mesh.edges, mesh.n_vertices, validate=validate)

    @classmethod
    def random_on_mesh(
        cls, mesh, n: int = 3, generator: torch.Generator | None = None, scale: float | None = None,
        batch_shape=(),
    ) -> "Connection":
        """:meth:`random` on ``mesh.edges`` with the dtype/device of ``mesh.vertices``."""
        v = mesh.vertices
        return cls.random(
            mesh.edges, mesh.n_vertices, n=n, generator=generator, scale=scale, dtype=v.dtype, device=v.device,
            batch_shape=batch_shape,
        )

    @classmethod
    def smooth_on_mesh(cls, mesh, smooth, method: str = "midpoint", steps: int = 512) -> "Connection":
        """:meth:`from_smooth` on ``mesh.vertices`` / ``mesh.edges``."""
        return cls.from_smooth(mesh.vertices, mesh.edges, smooth, method=method, steps=steps, n_vertices=mesh.n_vertices)
