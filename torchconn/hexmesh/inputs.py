"""The frame field a hex-meshing call is given, checked and brought to one frame per tet."""
from __future__ import annotations

import torch

__all__ = ["tet_frames_of"]


def tet_frames_of(mesh, frames) -> torch.Tensor:
    """Per-tet frames ``(T, 3, 3)`` float64 (CPU) from a ``FrameFieldResult`` on ``mesh``, per-tet
    ``(T, 3, 3)`` or per-vertex ``(V, 3, 3)`` frames (axes as columns), checked to be rotations.

    Raises:
        ValueError: a field on another mesh, a wrong shape, non-finite entries, not rotations.
    """
    from ..frames.design import tet_frames

    if hasattr(frames, "tet_frames") and hasattr(frames, "mesh"):
        res_mesh = frames.mesh
        if res_mesh is not mesh and (res_mesh.n_tets != mesh.n_tets or res_mesh.n_vertices != mesh.n_vertices):
            raise ValueError(f"the frame field lives on another mesh ({res_mesh.n_vertices} vertices, "
                             f"{res_mesh.n_tets} tets) than the one given ({mesh.n_vertices}, {mesh.n_tets})")
        frames = frames.tet_frames
    Fr = torch.as_tensor(frames)
    if Fr.dim() != 3 or Fr.shape[1:] != (3, 3):
        raise ValueError(f"frames must be a FrameFieldResult or a (T, 3, 3) / (V, 3, 3) tensor, got shape {tuple(Fr.shape)}")
    Fr = Fr.detach().to("cpu", torch.float64)
    if Fr.shape[0] == mesh.n_tets:
        out = Fr
    elif Fr.shape[0] == mesh.n_vertices:
        out = tet_frames(Fr, mesh.to("cpu", torch.float64) if mesh.vertices.dtype != torch.float64 else mesh)
    else:
        raise ValueError(f"frames has {Fr.shape[0]} rows, but the mesh has {mesh.n_tets} tets and {mesh.n_vertices} "
                         f"vertices: the field lives on another mesh")
    if not torch.isfinite(out).all():
        raise ValueError("frames has non-finite entries")
    err = (out.transpose(1, 2) @ out - torch.eye(3, dtype=out.dtype)).abs().amax(dim=(1, 2))
    det = torch.linalg.det(out)
    bad = torch.nonzero((err > 1e-6) | (det <= 0)).flatten()
    if bad.numel():
        raise ValueError(f"frames must be rotations: {bad.numel()} are not (first rows {bad[:5].tolist()}, "
                         f"orthogonality error up to {float(err.max()):.2e}); project them with so3.project_to_rotation")
    return out
