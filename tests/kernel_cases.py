"""Helpers shared by the custom-op test files (``tests/test_ops_library_*.py``, the frame kernels'):
the kernel switch with its skip, the parametrization over it, and the smallest mesh whose tets share
edges."""
from __future__ import annotations

import pytest
import torch

from torchconn.mesh import TetMesh
from torchconn.ops import compiled, native

#: ``on`` = the compiled C kernels, ``off`` = the generic torch kernels
SWITCH = [pytest.param(True, id="compiled"), pytest.param(False, id="generic")]


def switch(on: bool, library: str, source: str):
    """``torchconn.ops.compiled(on)``; skips (naming ``source``) when ``on`` and the C library
    ``library`` cannot be built here."""
    if on and native.library(library) is None:
        pytest.skip(f"no C compiler (or TORCHCONN_NATIVE=0): {source} cannot be built")
    return compiled(on)


def assert_kernels_agree(call, dtype: torch.dtype):
    """Run ``call(with_grad)`` (an op returning ``(value, *gradients)``) with the compiled and the generic
    kernels, with and without the forward's gradients, and assert both kernels agree (relative to
    the largest entry; 2e-5 in float32, 1e-12 in float64). Returns the compiled run with gradients."""
    res = {}
    for on in (True, False):
        for with_grad in (True, False):
            with compiled(on):
                res[on, with_grad] = call(with_grad)
    tol = 2e-5 if dtype == torch.float32 else 1e-12
    for with_grad in (True, False):
        for a, b in zip(res[True, with_grad], res[False, with_grad]):
            assert a.shape == b.shape
            if b.numel():
                torch.testing.assert_close(a, b, atol=tol * max(1.0, float(b.abs().max())), rtol=0)
    return res[True, True]


def two_tets(dtype: torch.dtype = torch.float64) -> TetMesh:
    """Two tets sharing a face: the smallest mesh where tets share edges (fast gradgradcheck)."""
    v = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.2]], dtype=dtype)
    return TetMesh(v, [[0, 1, 2, 3], [1, 2, 3, 4]], reorient=True)
