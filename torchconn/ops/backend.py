"""The one switch between the compiled C kernels and the torch kernels (``torch.backends``-style).

Every op of :mod:`torchconn.ops` that has a compiled kernel asks :func:`can_use_compiled` and
nothing else; no public function takes a ``native=`` flag. The switch is global (all threads)
and starts from the environment: ``TORCHCONN_NATIVE=0`` (or ``false``/``off``/``no``) turns
it off, so that the C sources are never built.

>>> with torchconn.ops.compiled(False):   # the torch kernels, e.g. as a test reference
...     R_ref = so3.exp(omega)
"""
from __future__ import annotations

import contextlib
import os
import threading

import torch

from . import native

__all__ = ["compiled_enabled", "set_compiled", "compiled", "can_use_compiled"]

_LOCK = threading.Lock()


def _from_env() -> bool:
    return os.environ.get("TORCHCONN_NATIVE", "1").strip().lower() not in ("0", "false", "off", "no")


_ENABLED = _from_env()


def compiled_enabled() -> bool:
    """Whether the compiled kernels may be used (they still need a built library and CPU tensors)."""
    return _ENABLED


def set_compiled(enabled: bool) -> None:
    """Turn the compiled kernels on or off for the whole process."""
    global _ENABLED
    with _LOCK:
        _ENABLED = bool(enabled)


@contextlib.contextmanager
def compiled(enabled: bool):
    """Context manager: the switch set to ``enabled`` inside, the previous state restored on exit."""
    global _ENABLED
    with _LOCK:
        prev, _ENABLED = _ENABLED, bool(enabled)
    try:
        yield
    finally:
        with _LOCK:
            _ENABLED = prev


def _plain(t: torch.Tensor) -> bool:
    """Not a tensor of a vmap / torch.func transform (those have no data pointer for C)."""
    f = torch._C._functorch
    return not (f.is_functorch_wrapped_tensor(t) or f.is_legacy_batchedtensor(t))


def can_use_compiled(lib_name: str, *tensors: torch.Tensor) -> bool:
    """Whether the compiled ``csrc/<lib_name>.c`` may run on ``tensors``.

    Asked only inside the CPU kernels of the ``torchconn::`` custom ops (below autograd and
    below vmap: their tensors are plain; under ``torch.compile`` the ops are opaque and their
    CPU kernels run with real tensors at run time, the fake kernels at trace time). True when
    the switch is on, no ``torch.compile`` trace is running, all tensors are plain (no vmap /
    torch.func wrapper), on the CPU, float32 or float64 of one dtype, and the library is built
    (:func:`torchconn.ops.native.library`). Higher derivatives never need a C kernel: the
    backward ops differentiate their torch formulas.
    """
    if not _ENABLED or not tensors or torch.compiler.is_compiling():
        return False
    dt = tensors[0].dtype
    if dt not in (torch.float32, torch.float64):
        return False
    if any(t.device.type != "cpu" or t.dtype != dt or not _plain(t) for t in tensors):
        return False
    return native.library(lib_name) is not None
