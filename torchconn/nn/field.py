"""Learnable connection: :class:`ConnectionField`, the ``nn.Module`` parametrization
``edge_rot = exp(hat(params))`` of a :class:`~torchconn.dec.connection.Connection` (report Sec. 3.1;
conventions of :mod:`torchconn.dec.connection`)."""
from __future__ import annotations

from typing import Any

import torch

from ..dec.connection import Connection, _as_edges, _check_edges, _exp_params, _log_params
from ..lie import son
from ..tolerances import get_eps

__all__ = ["ConnectionField"]


class ConnectionField(torch.nn.Module):
    """Learnable connection: ``edge_rot = exp(hat(params))``, one skew vector per edge.

    Args:
        edges: ``(E, 2)`` canonical edges (stored as a buffer).
        n_vertices: ``V``.
        n: rank (default 3).
        init: ``None`` (identity, ``params = 0``), a :class:`Connection` on the same edges
            (batched or not), a ``(*batch, E, n(n-1)/2)`` parameter tensor, or a
            ``(*batch, E, n, n)`` rotation tensor. Rotations are converted by the principal
            logarithm (``|params| <= pi``; at angle exactly pi either sign of the axis may be
            returned — both exponentiate to the same rotation) after a check that they are
            rotations (``ValueError`` naming the edge indices of NaN/inf, non-orthogonal or
            ``det -1`` matrices); parameters must be finite.
        dtype, device: of the parameters (default: those of ``init`` when it is a tensor or a
            connection, else the default dtype).
        batch_shape: leading batch dims of the field, a batch of independent connections on the
            same edges (like the leading dims of roma / pytorch3d rotations): ``params`` has
            shape ``(*batch_shape, E, n(n-1)/2)`` and :meth:`forward` returns a
            :class:`Connection` with ``edge_rot (*batch_shape, E, n, n)``, which every operator
            and module accepts. Default: the leading dims of ``init`` (``()`` without ``init``).
            ``init=None`` with a ``batch_shape`` gives identities for every item; a given
            ``batch_shape`` must equal the leading dims of a tensor/connection ``init``.

    ``forward()`` returns a :class:`Connection` whose ``edge_rot`` is differentiable in
    ``params`` (Rodrigues for ``n = 3``, :func:`son.exp_params` otherwise; finite gradients at
    ``params = 0``). Parameter order: :func:`so3.hat` for ``n = 3``, :func:`son.hat` otherwise.

    ``device="meta"`` builds a shapes-only field (e.g. to size a model before materializing
    it): the checks that need values — edge ranges and duplicates, finiteness of the
    parameters, the rotation check of a rotation ``init`` — are skipped there.
    """

    def __init__(
        self,
        edges: Any,
        n_vertices: int,
        n: int = 3,
        init: Any = None,
        dtype: torch.dtype | None = None,
        device=None,
        batch_shape: Any = None,
    ):
        super().__init__()
        if isinstance(init, Connection):
            dtype = dtype or init.dtype
            device = device if device is not None else init.device
        elif isinstance(init, torch.Tensor):
            dtype = dtype or (init.dtype if init.is_floating_point() else None)
            device = device if device is not None else init.device
        dtype = dtype or torch.get_default_dtype()
        edges = _as_edges(edges, device=device)
        sorted_keys, perm = _check_edges(edges, n_vertices)
        E, m = edges.shape[0], son.dim(n)
        self.n = int(n)
        self.n_vertices = int(n_vertices)
        self.register_buffer("edges", edges)
        # edge lookup of :meth:`Connection.transport`, built once (rebuilt after load_state_dict)
        self.register_buffer("_sorted_keys", sorted_keys, persistent=False)
        self.register_buffer("_perm", perm, persistent=False)
        self.register_load_state_dict_post_hook(ConnectionField._rebuild_lookup)
        given = None if batch_shape is None else tuple(int(b) for b in batch_shape)
        meta = edges.device.type == "meta"

        def shape_error(what: str, got) -> ValueError:
            b = "".join(f"{x}, " for x in (given or ()))
            lead = "*batch_shape, " if given is None else b
            return ValueError(
                f"ConnectionField init: {what} must have shape ({lead}{E}, {m}) (parameters) or "
                f"({lead}{E}, {n}, {n}) (rotations) with E={E}"
                f"{'' if given is None else f', batch_shape={given}'}, got {tuple(got)}")

        if init is None:
            params = torch.zeros(*(given or ()), E, m, dtype=dtype, device=edges.device)
        elif isinstance(init, Connection):
            if init.n != n:
                raise ValueError(f"init connection has rank {init.n}, field has n={n}")
            if init.edges.shape != edges.shape or (not meta and init.edges.device.type != "meta"
                                                   and not torch.equal(init.edges.to(edges.device), edges)):
                raise ValueError("init connection is defined on different edges than the field")
            if given is not None and tuple(init.batch_shape) != given:
                raise shape_error("the init connection's edge_rot", init.edge_rot.shape)
            params = self._log_checked(init.edge_rot.detach().to(dtype=dtype, device=edges.device),
                                       edges, (sorted_keys, perm), "ConnectionField init (Connection)")
        elif isinstance(init, torch.Tensor):
            t = init.detach().to(dtype=dtype, device=edges.device)
            if t.dim() >= 2 and t.shape[-2:] == (E, m) and (given is None or tuple(t.shape[:-2]) == given):
                if not meta:
                    finite = torch.isfinite(t).reshape(-1, E, m).all(-1).all(0)
                    if not bool(finite.all()):
                        bad = torch.nonzero(~finite).flatten()
                        raise ValueError(
                            f"ConnectionField init: parameters (..., E, {m}) have non-finite entries (NaN/inf) at "
                            f"edge indices {bad[:10].tolist()}{' ...' if bad.numel() > 10 else ''} "
                            f"({bad.numel()} of {E} edges); pass finite skew parameters"
                        )
                params = t.clone()
            elif t.dim() >= 3 and t.shape[-3:] == (E, n, n) and (given is None or tuple(t.shape[:-3]) == given):
                params = self._log_checked(t, edges, (sorted_keys, perm), "ConnectionField init")
            else:
                raise shape_error("init tensor", t.shape)
        else:
            raise TypeError(
                f"init must be None, a Connection or a tensor, got {type(init).__name__}; convert an "
                f"array first, e.g. torch.as_tensor(init, dtype=torch.float64)"
            )
        self.params = torch.nn.Parameter(params)

    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch dims of the field (``params.shape[:-2]``)."""
        return self.params.shape[:-2]

    def _log_checked(self, R: torch.Tensor, edges: torch.Tensor, lookup, name: str) -> torch.Tensor:
        """Principal-log parameters of ``R (..., E, n, n)`` after checking that they are rotations.

        The logarithm is meaningless (and can be NaN) for reflections, non-orthogonal or
        non-finite matrices (:func:`torchconn.lie.so3.log`), so the init rotations are
        validated here, once, where they enter the library: ``ValueError`` naming the edge
        indices and the defect (:meth:`Connection.check_rotations`). The tolerance is the
        float32 one of ``get_eps("rotation")`` (or the dtype's, if looser): rotations saved in
        single precision and cast to float64 are accepted, and their log is that of the
        nearest rotation to first order. Synchronizes (one-time setup); skipped on ``meta``.
        """
        atol = max(get_eps("rotation", R.dtype), get_eps("rotation", torch.float32))
        Connection._trusted(R, edges, self.n_vertices, lookup).check_rotations(atol=atol, name=name)
        return _log_params(R)

    @staticmethod
    def _rebuild_lookup(module: "ConnectionField", incompatible_keys) -> None:
        """Re-validate loaded edges and rebuild the lookup buffers (load_state_dict post-hook)."""
        keys, perm = _check_edges(module.edges, module.n_vertices)
        module._sorted_keys = keys
        module._perm = perm

    @classmethod
    def from_connection(cls, conn: Connection) -> "ConnectionField":
        """Field with ``exp(params) == conn.edge_rot`` (principal log, see class docstring); keeps
        the connection's batch dims."""
        return cls(conn.edges, conn.n_vertices, n=conn.n, init=conn)

    def edge_rotations(self) -> torch.Tensor:
        """``exp(hat(params))`` -> ``(*batch_shape, E, n, n)`` rotations ``R_ij`` of the canonical edges."""
        return _exp_params(self.params, self.n)

    def forward(self) -> Connection:
        """The current :class:`Connection` (differentiable in ``params``; ``edge_rot`` of shape
        ``(*batch_shape, E, n, n)``)."""
        R = self.edge_rotations()
        return Connection._trusted(R, self.edges, self.n_vertices, (self._sorted_keys, self._perm))

    def extra_repr(self) -> str:
        b = f"batch_shape={tuple(self.batch_shape)}, " if len(self.batch_shape) else ""
        return f"{b}n={self.n}, n_vertices={self.n_vertices}, n_edges={self.edges.shape[0]}"
