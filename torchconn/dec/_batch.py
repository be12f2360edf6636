"""Leading batch dimensions of a connection, shared by the operators of :mod:`torchconn.dec`.

Every operator takes the connection as ``(*batch, E, n, n)`` rotations of the canonical edges
of one mesh (``batch`` may be empty) and returns its values with the same leading dims,
``(*batch, F, n, n)``, ``(*batch, T, n)``, ... . Mesh data (vertex positions, index tables)
carries no batch dims and is shared by every item.

The ops of :mod:`torchconn.ops` (``torchconn::`` custom ops) take the leading batch dims
themselves and have vmap rules, so the batched tensor goes straight to the op. :func:`ask_op`
falls back to the generic torch formula of the caller (which broadcasts over the leading dims)
only when the op returns ``None`` (it does not apply: rank, cut, mesh kind). Forward mode
(``torch.func.jvp``, ``jacfwd``, ``torch.autograd.forward_ad``) goes to the op as well: the
public functions of :mod:`torchconn.ops` call their op through an ``autograd.Function`` with
an exact ``jvp`` rule in eager mode. (The generic formula would be the wrong fallback: the
fused tet closed form and the dense generic operators agree on rotations only, so off SO(3)
their derivatives differ and ``jacfwd`` would disagree with ``jacrev``.)

Every exception of an op propagates.
"""
from __future__ import annotations

from typing import Callable

import torch

__all__ = ["edge_batch", "check_frames", "batch_text", "ask_op", "expand_to", "on_device"]


def batch_text(batch: tuple[int, ...]) -> str:
    """``"2, 3, "`` for ``(2, 3)``, ``""`` for ``()``: the batch prefix of a shape in messages."""
    return "".join(f"{b}, " for b in batch)


def edge_batch(R, E: int, fn: str, *, n: int | None = None, what: str = "edge_rot") -> tuple[int, ...]:
    """Check ``R`` is a floating ``(*batch, E, n, n)`` tensor; return ``batch``.

    Raises ``ValueError`` whose message names the expected shape with the batch dims of the
    input (``(2, 604, 3, 3)``) and the given shape. Reads no data (no device sync).
    """
    if not isinstance(R, torch.Tensor):
        raise TypeError(f"{fn}: {what} must be a tensor of shape (..., E, n, n), got {type(R).__name__}")
    nn_ = "n, n" if n is None else f"{n}, {n}"
    if R.ndim < 3 or R.shape[-1] != R.shape[-2] or (n is not None and R.shape[-1] != n):
        raise ValueError(f"{fn}: {what} must have shape (..., {E}, {nn_}) (optional leading batch dims, "
                         f"one rotation per mesh edge), got {tuple(R.shape)}")
    batch = tuple(R.shape[:-3])
    if R.shape[-3] != E:
        short = f" (mesh edge index {E - 1} out of range)" if R.shape[-3] < E else ""
        lead = f"leading batch dims {batch}, " if batch else ""
        raise ValueError(f"{fn}: {what} must have shape ({batch_text(batch)}{E}, {R.shape[-1]}, {R.shape[-1]}) "
                         f"({lead}one rotation per mesh edge in mesh.edges order), got "
                         f"{tuple(R.shape)}: {R.shape[-3]} rotations for {E} edges{short}")
    return batch


def check_frames(frames, V: int, n: int, batch: tuple[int, ...], fn: str):
    """Check ``frames`` is ``None``, ``(V, n, n)`` (shared by every item of the batch) or
    ``(*batch, V, n, n)`` (one frame field per item); raise ``ValueError`` naming both shapes."""
    if frames is None:
        return None
    shape = tuple(frames.shape)
    if shape[-3:] != (V, n, n) or shape[:-3] not in ((), tuple(batch)):
        alt = f" or ({batch_text(batch)}{V}, {n}, {n})" if batch else ""
        raise ValueError(f"{fn}: frames must have shape ({V}, {n}, {n}){alt} (one frame per mesh vertex"
                         f"{', optionally one field per batch item' if batch else ''}), got {shape}")
    return frames


def ask_op(call: Callable, R: torch.Tensor, *others):
    """``call()`` (an op of :mod:`torchconn.ops`); ``None`` (the op does not apply) tells the
    caller to use its generic formula. ``R`` and ``others`` are the op's tensor arguments."""
    return call()


def expand_to(x: torch.Tensor, batch: tuple[int, ...]) -> torch.Tensor:
    """``x`` with the leading dims ``batch`` added (a view; no copy)."""
    return x.expand(*batch, *x.shape) if batch else x


def on_device(mesh, name: str, device: torch.device) -> torch.Tensor:
    """``getattr(mesh, name)`` on ``device``: no copy when it is there already, else moved once
    and cached per mesh and device (``ops._cache.require``) so a CPU mesh used with CUDA
    connections is not copied at every call."""
    t = getattr(mesh, name)
    if t.device == device:
        return t
    from ..ops._cache import require
    return require(mesh, f"dec.{name}.{device}", lambda m: getattr(m, name).to(device))
