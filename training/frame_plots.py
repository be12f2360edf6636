"""Figures of a ``train_frames`` run: the loss history and the singular curves (matplotlib, Agg).

Both write a PNG atomically (:func:`training.io_utils.atomic_write`); matplotlib is imported on
call, so importing this module does not need it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from . import io_utils

__all__ = ["plot_loss", "plot_singularities"]


def plot_loss(path: Path, history: dict) -> None:
    """Semilog plot of every recorded loss term per step (``history``: ``{term: [value per step]}``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for k, vals in history.items():
        v = np.asarray(vals, dtype=float)
        if v.size and np.any(v > 0):
            ax.semilogy(np.arange(v.size), np.where(v > 0, v, np.nan), label=k, lw=2 if k == "total" else 1)
    ax.set_xlabel("step")
    ax.set_ylabel("loss term (unweighted; total weighted)")
    ax.set_title("train_frames loss")
    if ax.lines:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no optimization steps", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    io_utils.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


def plot_singularities(path: Path, mesh, singular_faces: torch.Tensor) -> None:
    """Boundary vertices (points) and singular curves: for every singular face ``(S, 3)`` (vertex
    indices) the dual segments from the barycenters of its tets through the face barycenter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    P = mesh.vertices.detach().cpu().double().numpy()
    bv = mesh.boundary_vertices.cpu().numpy()
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    ax.scatter(P[bv, 0], P[bv, 1], P[bv, 2], s=2, c="0.45", alpha=0.5, linewidths=0)
    S = singular_faces.cpu().numpy().reshape(-1, 3)
    if S.shape[0]:
        faces = mesh.faces.cpu().numpy()
        key = lambda a: (a[:, 0] * P.shape[0] + a[:, 1]) * P.shape[0] + a[:, 2]  # noqa: E731
        idx = np.searchsorted(key(faces), key(np.sort(S, axis=1)))
        fb = mesh.face_barycenters.detach().cpu().double().numpy()[idx]
        tb = mesh.tet_barycenters.detach().cpu().double().numpy()
        ft = mesh.face_tets.cpu().numpy()[idx]
        segs = [np.stack([tb[ft[:, c][ft[:, c] >= 0]], fb[ft[:, c] >= 0]], 1) for c in range(2)]
        segs = np.concatenate(segs, 0)
        ax.add_collection3d(Line3DCollection(segs, colors="r", linewidths=1.5))
    ax.set_title(f"singular curves ({S.shape[0]} singular faces)")
    lo, hi = P.min(0), P.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    fig.tight_layout()
    io_utils.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)
