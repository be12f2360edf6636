"""Kernels: the one place that chooses and dispatches compiled or torch implementations.

One module per op family, each op deciding its own path in one place:

* :mod:`.so3`: ``exp``, ``log``, ``sqrt``, ``half_exp`` (compiled ``csrc/so3.c`` or torch);
* :mod:`.curvature`: face curvature of sorted-triangle meshes (fused torch kernel);
* :mod:`.torsion`: per-edge solder forms and face torsion (fused torch kernels);
* :mod:`.tet`: the averaged ``d∇d∇θ`` per tet (fused torch kernel, :class:`~.tet.TetKernel`);
* :mod:`.frame_loss`: the compiled frame-field loss terms (``csrc/frame_loss.c``).

:mod:`.backend` holds the one global switch for the compiled kernels (:func:`compiled_enabled`,
:func:`set_compiled`, the context manager :func:`compiled`; initialized from the environment
variable ``TORCHCONN_NATIVE``) and the one predicate every op asks
(:func:`can_use_compiled`); :mod:`.native` builds and loads the C sources of ``csrc/``.
Ops that apply only to some inputs return ``None`` elsewhere, and their caller evaluates its
generic formula. This package imports nothing of torchconn but :mod:`torchconn.tolerances`.
"""
from . import backend, curvature, frame_loss, native, so3, tet, torsion
from .backend import can_use_compiled, compiled, compiled_enabled, set_compiled

__all__ = [
    "backend",
    "native",
    "so3",
    "curvature",
    "torsion",
    "tet",
    "frame_loss",
    "compiled_enabled",
    "set_compiled",
    "compiled",
    "can_use_compiled",
]
