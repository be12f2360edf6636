"""Kernels: the one place that chooses and dispatches compiled or torch implementations.

:mod:`.native` builds the C sources of ``csrc/`` once with the system compiler and loads them;
:mod:`.fast` holds the fused torch kernels with hand-written backward passes and routes CPU
float32/float64 calls to the compiled kernels when they are available.
"""
from . import fast, native

__all__ = ["fast", "native"]
