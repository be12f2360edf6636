"""Figures of a ``train_frames`` run: the loss history and the singular curves (matplotlib, Agg).

Each writes a PNG atomically (:func:`training.io_utils.atomic_write`); matplotlib is imported on
call, so importing this module does not need it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import io_utils

__all__ = ["plot_loss", "plot_singularities", "plot_singular_graph", "CURVE_COLORS"]

CURVE_COLORS = {"valence3": "tab:blue", "valence5": "tab:red", "half": "tab:green",
                "complex": "black", "mixed": "tab:purple"}
"""Colour of a singular curve by its label (:data:`torchconn.frames.singular.CURVE_TYPES`)."""


def plot_loss(path: Path, history: dict, histories: dict | None = None, chosen: dict | None = None) -> None:
    """Semilog plot of the loss terms per step of the connection optimization.

    ``history``: ``{term: [value per step]}``, the optimization that made the returned field.
    ``histories``: ``{start: history}`` of every start (one panel each, the winner's first);
    ``chosen``: ``metrics["chosen"]`` of :func:`torchconn.frames.design` (which candidate won,
    how it was chosen): the title says it.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = dict(histories) if histories else {"": history}
    win = chosen.get("start") if chosen else None
    order = sorted(panels, key=lambda k: k != win)
    fig, axes = plt.subplots(1, len(order), figsize=(6 * len(order), 4.2), squeeze=False)
    for ax, start in zip(axes[0], order):
        hist = panels[start]
        for k, vals in hist.items():
            v = np.asarray(vals, dtype=float)
            if v.size and np.any(v > 0):
                ax.semilogy(np.arange(v.size), np.where(v > 0, v, np.nan), label=k, lw=2 if k == "total" else 1)
        ax.set_xlabel("step")
        ax.set_ylabel("loss term (unweighted; total weighted)")
        tag = f"start {start}" if start else "loss"
        if start and start == win:
            tag += ": made the returned field"
        ax.set_title(tag, fontsize=10)
        if ax.lines:
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, "no optimization steps", ha="center", va="center", transform=ax.transAxes)
    if chosen:
        fig.suptitle(f"connection optimization; returned: {chosen.get('label')} (chosen by {chosen.get('by')}: "
                     f"{chosen.get('reason')})", fontsize=10)
    fig.tight_layout()
    io_utils.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


def _boundary_axes(mesh):
    """A 3D axes with the boundary surface drawn translucent and equal axis ranges."""
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    P = mesh.vertices.detach().cpu().double().numpy()
    fig = plt.figure(figsize=(6.5, 6))
    ax = fig.add_subplot(projection="3d")
    tri = P[mesh.boundary_faces.cpu().numpy()]
    ax.add_collection3d(Poly3DCollection(tri, facecolors=(0.6, 0.6, 0.65, 0.06),
                                         edgecolors=(0.4, 0.4, 0.45, 0.05), linewidths=0.3))
    lo, hi = P.min(0), P.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    return fig, ax


def _save(fig, path) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    io_utils.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    plt.close(fig)


def plot_singularities(path: Path, mesh, singular) -> None:
    """``singularities.png``: the boundary drawn translucent and the singular curves.

    ``singular`` is either a :class:`~torchconn.frames.singular.SingularGraph` (curves coloured
    by type, :func:`plot_singular_graph`) or the singular faces ``(S, 3)`` (vertex indices), drawn
    as the dual segments from the barycenters of their tets through the face barycenter.
    """
    from torchconn.frames.singular import SingularGraph

    if isinstance(singular, SingularGraph):
        plot_singular_graph(path, mesh, singular)
        return
    import matplotlib

    matplotlib.use("Agg")
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    P = mesh.vertices.detach().cpu().double().numpy()
    fig, ax = _boundary_axes(mesh)
    S = singular.cpu().numpy().reshape(-1, 3)
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
    _save(fig, path)


def plot_singular_graph(path: Path, mesh, graph) -> None:
    """The singular graph over the translucent boundary: each curve a polyline coloured by its
    label (:data:`CURVE_COLORS`: valence 3 blue, valence 5 red, half turn green, complex black,
    mixed purple), zipper faces (quarter turns whose axis is not tangent-dominant) as orange dots,
    junctions as black dots; the title names the counts."""
    import matplotlib

    matplotlib.use("Agg")
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    fig, ax = _boundary_axes(mesh)
    for label, color in CURVE_COLORS.items():
        segs = [np.stack([c.points[:-1].detach().cpu().double().numpy(),
                          c.points[1:].detach().cpu().double().numpy()], 1)
                for c in graph.curves if c.label == label and c.points.shape[0] > 1]
        if segs:
            n = len(segs)
            ax.add_collection3d(Line3DCollection(np.concatenate(segs), colors=color, linewidths=1.8,
                                                 label=f"{label} ({n} curve{'s' * (n > 1)})"))
    fb = mesh.face_barycenters.detach().cpu().double().numpy()
    zip_faces = graph.face_index[(graph.face_type == 1) & ~graph.face_valid].cpu().numpy()
    if zip_faces.size:
        z = fb[zip_faces]
        ax.scatter(z[:, 0], z[:, 1], z[:, 2], s=10, c="tab:orange", label=f"zipper faces ({z.shape[0]})")
    if graph.junctions:
        J = np.stack([j["point"].detach().cpu().double().numpy() for j in graph.junctions])
        ax.scatter(J[:, 0], J[:, 1], J[:, 2], s=18, c="k", marker="o", label=f"junctions ({J.shape[0]})")
    c = graph.counts()
    bt = c["n_singular_faces_by_type"]
    ax.set_title(f"{c['n_singular_curves']} singular curves, faces quarter/half/complex "
                 f"{bt['quarter']}/{bt['half']}/{bt['complex']}, valid {c['valid_fraction']:.2f}", fontsize=9)
    if ax.collections[1:]:
        ax.legend(fontsize=7, loc="upper left")
    _save(fig, path)
