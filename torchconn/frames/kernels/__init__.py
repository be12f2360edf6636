"""The frame-field kernels: custom ops of the ``torchconn::`` registry that only the frames use.

Declared like every op of :mod:`torchconn.ops` (one ``torch.library`` schema, a generic torch
kernel on every device, a CPU kernel running compiled C when
:func:`torchconn.ops.backend.can_use_compiled` allows it, a fake kernel, exact autograd, a vmap
rule); their C sources live in ``csrc/`` next to this file and are built by
:mod:`torchconn.ops.native` like the core kernels (:func:`~torchconn.ops.native.register_source`):

* :mod:`.frame_loss`: ``frame_loss``, the fast path of the frame-field loss terms ``smooth``,
  ``tie``, ``flat``, ``torsion``, ``dirichlet`` (:class:`torchconn.frames.loss.FrameFieldLoss`;
  ``csrc/frame_loss.c``; generic terms in ``_frame_loss_torch``);
* :mod:`.edge_terms`: ``matched_edge_terms``, the angle + Dirichlet objective of the frame-field
  quality paths with fixed matchings (``csrc/edge_terms.c``);
* :mod:`.tet_frames`: ``smooth_tet_frames``, per-tet frames from per-vertex frames by a
  differentiable polar factor (the frames the seamless map's energy term reads;
  :func:`torchconn.hexmesh.energy.smooth_tet_frames`; ``csrc/tet_frames.c``; no vmap rule: no batch
  dimensions).
"""
from pathlib import Path

from . import edge_terms, frame_loss, tet_frames

#: Folder of the C sources of the frame-field kernels (each op module registers its own file).
CSRC = Path(__file__).resolve().parent / "csrc"

__all__ = ["CSRC", "frame_loss", "edge_terms", "tet_frames"]
