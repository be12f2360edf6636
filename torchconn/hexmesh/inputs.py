"""The frame field a hex-meshing call is given, checked and brought to one frame per tet.

The home of the frames' error messages: :func:`frames_defects` says what is wrong with an array
of frames in words (its shape against the mesh's, non-finite rows, rows that are not rotations
sorted into reflections, scaled rotations and the rest), and :func:`tet_frames_of` raises it;
the hex job (``training/hex_mesh.py``) prefixes the same sentences with the file they came from.
"""
from __future__ import annotations

import numpy as np
import torch

from ..tolerances import get_eps

__all__ = ["tet_frames_of", "frames_defects", "rotation_defects"]


def _rotation_atol() -> float:
    """``||F^T F - I||_F`` accepted for a rotation: the registry's float32 ``rotation`` tolerance
    (1e-4), whatever the dtype, as ``so3.log`` does: frames of a float32 run saved as float64
    pass; reflections, scaled, sheared and zero matrices are far outside it."""
    return get_eps("rotation", torch.float32)


def rotation_defects(F, *, per: str = "frame") -> str | None:
    """``None`` when every ``F (N, 3, 3)`` (finite) is a rotation, else one sentence naming how
    many of the ``N`` are not and of which kind, with the first rows of each kind:

    * reflections: orthogonal up to scale with ``det < 0`` (an axis flipped);
    * scaled rotations: ``F = s R`` with ``R`` a rotation and ``s != 1`` (the scale is named);
    * not orthogonal: anything else (sheared, singular), with the largest ``||F^T F - I||_F``.

    ``per`` names a row in the sentence (``"per-vertex frame"``, ``"per-tet frame"``).
    """
    A = torch.as_tensor(F).detach().to("cpu", torch.float64).reshape(-1, 3, 3)
    atol = _rotation_atol()
    eye = torch.eye(3, dtype=A.dtype)
    M = A.transpose(1, 2) @ A
    err = (M - eye).flatten(1).norm(dim=1)
    s2 = M.diagonal(dim1=1, dim2=2).mean(1)
    # orthogonal up to a scale s: F^T F = s^2 I (relative residual within the tolerance)
    scaled_orth = ((M - s2[:, None, None] * eye).flatten(1).norm(dim=1) <= atol * s2) & (s2 > 0)
    det = torch.linalg.det(A)
    ok = (err <= atol) & (det > 0)
    if bool(ok.all()):
        return None
    reflection = ~ok & scaled_orth & (det < 0)
    scaled = ~ok & scaled_orth & (det > 0)
    other = ~ok & ~reflection & ~scaled

    def first(mask) -> str:
        return str(torch.nonzero(mask).flatten()[:5].tolist())

    parts, fixes = [], []
    if reflection.any():
        parts.append(f"{int(reflection.sum())} reflections (det < 0: an axis flipped; rows {first(reflection)})")
        fixes.append("negate one axis (column) of a reflection")
    if scaled.any():
        sc = s2[scaled].sqrt()
        lo, hi = float(sc.min()), float(sc.max())
        scale = f"scale {lo:.6g}" if np.isclose(lo, hi, rtol=1e-9) else f"scales {lo:.6g} to {hi:.6g}"
        parts.append(f"{int(scaled.sum())} scaled rotations ({scale}, not 1; rows {first(scaled)})")
        fixes.append("divide a scaled rotation by its scale")
    if other.any():
        parts.append(f"{int(other.sum())} not orthogonal (||F^T F - I|| up to {float(err[other].max()):.3g} > "
                     f"{atol:g}; rows {first(other)})")
        fixes.append("torchconn.so3.project_to_rotation gives the nearest rotation")
    n_bad = int((~ok).sum())
    return (f"frames must be rotations (orthonormal axes as columns, det +1): {n_bad} of {A.shape[0]} {per}s "
            f"are not: " + ", ".join(parts) + " (" + "; ".join(fixes) + ")")


def frames_defects(frames, mesh) -> tuple[str, str | None]:
    """``(per, problem)``: whether ``frames`` are per ``"vertex"`` or per ``"tet"`` of ``mesh``,
    and ``None`` or one sentence on what is wrong (shape, non-finite rows, not rotations).

    The shape sentence names the expected and the given shape; a ``(N, 3, 3)`` array whose ``N``
    is neither the mesh's vertex nor its tet count is called a field of another mesh.
    """
    V, T = mesh.n_vertices, mesh.n_tets
    Fr = torch.as_tensor(frames)
    shape = tuple(Fr.shape)
    want = f"({V}, 3, 3) per vertex or ({T}, 3, 3) per tet"
    if Fr.dim() != 3 or shape[1:] != (3, 3):
        return "", f"frames have shape {shape}, expected {want} (axes as the columns of 3x3 matrices)"
    if shape[0] not in (V, T):
        return "", (f"frames have shape {shape}, expected {want}: {shape[0]} frames fit neither the mesh's "
                    f"{V} vertices nor its {T} tets (a field of another mesh?)")
    if not (Fr.is_floating_point() or Fr.dtype in (torch.int32, torch.int64)):
        return "", f"frames must hold real numbers, got dtype {Fr.dtype}"
    per = "tet" if shape[0] == T else "vertex"  # per tet when V == T, as before
    A = Fr.detach().to("cpu", torch.float64)
    bad = torch.nonzero(~torch.isfinite(A).flatten(1).all(1)).flatten()
    if bad.numel():
        return per, (f"frames have non-finite entries (NaN/inf): {bad.numel()} of {shape[0]} per-{per} frames, "
                     f"first rows {bad[:5].tolist()}")
    return per, rotation_defects(A, per=f"per-{per} frame")


def tet_frames_of(mesh, frames) -> torch.Tensor:
    """Per-tet frames ``(T, 3, 3)`` float64 (CPU) from a ``FrameFieldResult`` on ``mesh``, per-tet
    ``(T, 3, 3)`` or per-vertex ``(V, 3, 3)`` frames (axes as columns), checked to be rotations
    (:func:`frames_defects`) before per-vertex frames become per-tet ones
    (:func:`torchconn.frames.octahedral.tet_frames`).

    Raises:
        ValueError: a field on another mesh, a wrong shape (expected and given), non-finite
            entries, frames that are not rotations (how many, and which kind).
    """
    from ..frames.octahedral import tet_frames

    if hasattr(frames, "tet_frames") and hasattr(frames, "mesh"):
        res_mesh = frames.mesh
        if res_mesh is not mesh and (res_mesh.n_tets != mesh.n_tets or res_mesh.n_vertices != mesh.n_vertices):
            raise ValueError(f"the frame field lives on another mesh ({res_mesh.n_vertices} vertices, "
                             f"{res_mesh.n_tets} tets) than the one given ({mesh.n_vertices}, {mesh.n_tets})")
        frames = frames.tet_frames
    per, problem = frames_defects(frames, mesh)
    if problem is not None:
        raise ValueError(problem)
    Fr = torch.as_tensor(frames).detach().to("cpu", torch.float64)
    if per == "tet":
        return Fr
    return tet_frames(Fr, mesh.to("cpu", torch.float64) if mesh.vertices.dtype != torch.float64 else mesh)
