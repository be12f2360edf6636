"""Kernels: the one registry of ``torchconn::`` custom ops and the one place that picks a kernel.

Every hot op is declared once with :func:`torch.library.custom_op` (namespace
:data:`._library.NAMESPACE`, ``torch.ops.torchconn.<name>``) with a generic torch
implementation (every device and dtype), a CPU kernel running the compiled C code of ``csrc/``
when the switch allows it, a fake implementation (meta, ``torch.compile``, ``export``), an
autograd registration whose backward is itself a custom op with exact derivatives (double
backward, ``create_graph``, Hessian-vector products), and a vmap rule (native leading batch dims):

* :mod:`.so3`: ``so3_exp``, ``so3_log``, ``so3_log_checked``, ``so3_sqrt`` (+ backward ops;
  ``csrc/so3.c``; generic formulas in ``_so3_formulas``);
* :mod:`.curvature`: ``face_curvature`` of sorted-triangle meshes (``csrc/curvature.c``);
* :mod:`.curvature_sqnorm`: ``face_curvature_sqnorm``, the weighted squared norm ``Σ_f w_f |H_f|²``
  of the face curvature per item, its gradient computed in the same C sweep over the edges;
* :mod:`.torsion`: ``face_torsion_sqrt``, the √R torsion (``csrc/torsion.c``: roots and solder forms
  per edge, a race-free backward over the edges' incident faces);
* :mod:`.tet`: ``tet_dd``, the averaged ``𝔡∇ Alt 𝔡∇ Alt θ̃`` per tet (``csrc/tet.c``; generic SoA
  kernel in ``_tet_soa``; tables in :class:`~.tet.TetKernel`);
* :mod:`.tet_solder`: ``tet_dd_sqrt`` / ``tet_dd_rot`` / ``tet_dd_frames``, the same with ``θ̃`` (and
  ``√R``, or the solder form in a frame field) formed inside the kernel, and ``tet_dd_solder``, the
  mesh-level entry point;
* :mod:`.tet_sqnorm`: ``tet_dd_frames_sqnorm``, the weighted squared norm ``Σ_t w_t |d∇d∇θ_t|²`` of
  ``tet_dd_frames`` per item, its gradient computed in the same C sweep (the ``dnabla`` loss term).

The ops that only the frame-field method uses (``frame_loss``, ``matched_edge_terms``) are
declared the same way in :mod:`torchconn.frames.kernels`, with their C sources there
(:func:`.native.register_source`).

:mod:`.backend` holds the one global switch for the compiled kernels (:func:`compiled_enabled`,
:func:`set_compiled`, the context manager :func:`compiled`; initialized from the environment
variable ``TORCHCONN_NATIVE``) and the one predicate the CPU kernels ask
(:func:`can_use_compiled`); :mod:`.native` builds the C sources with the system compiler at
first use and declares each C signature once (:func:`.native.declare`); ``_library`` holds the
namespace, the shared vmap rule and the forward-mode helper. The public functions of each
module keep mesh objects out of the ops (index tables built once per mesh are op arguments);
some return ``None`` where they do not apply, and their caller evaluates its generic formula.
This package imports nothing of torchconn but :mod:`torchconn.tolerances`.
"""
from . import backend, curvature, curvature_sqnorm, native, so3, tet, tet_solder, tet_sqnorm, torsion
from .backend import can_use_compiled, compiled, compiled_enabled, set_compiled

__all__ = [
    "backend",
    "native",
    "so3",
    "curvature",
    "curvature_sqnorm",
    "torsion",
    "tet",
    "tet_solder",
    "tet_sqnorm",
    "compiled_enabled",
    "set_compiled",
    "compiled",
    "can_use_compiled",
]
