"""Validation shared by :mod:`.so3` and :mod:`.son` (kept below both so neither imports the other)."""
from __future__ import annotations

import torch

from ..tolerances import get_eps

__all__ = ["check_rotation", "check_float_tensor"]


def check_float_tensor(x, fn: str, arg: str) -> None:
    """Raise ``TypeError`` unless ``x`` is a real floating-point ``torch.Tensor``.

    The lie functions take tensors only, like the ``torch`` functions they are built from:
    a NumPy array or a list is not converted (a silent ``torch.as_tensor`` would pick the
    device and, for lists, the dtype behind the caller's back). Integer, bool and complex
    dtypes are refused: the Taylor thresholds and tolerances exist for float16, bfloat16,
    float32 and float64 only. ``fn`` (e.g. ``"so3.exp"``) and ``arg`` (e.g. ``"omega"``) name
    the call in the message. No data is read (no device sync; fine under ``torch.compile``
    and ``vmap``).
    """
    if not isinstance(x, torch.Tensor):
        kind = f"{type(x).__module__}.{type(x).__name__}".replace("builtins.", "")
        raise TypeError(
            f"{fn}: {arg} must be a torch.Tensor, got {kind}; convert it first, e.g. "
            f"torch.as_tensor({arg}, dtype=torch.float64)"
        )
    if not x.is_floating_point():
        raise TypeError(
            f"{fn}: {arg} must be a floating-point tensor, got dtype {x.dtype}; pass a float "
            f"tensor, e.g. {arg}.to(torch.float64) or {arg}.to(torch.get_default_dtype())"
        )


def rotation_defects(R: torch.Tensor, atol: float):
    """Per-matrix defects of ``R (..., n, n)`` (no sync, no gradient):
    ``(non_finite, not_orthogonal, reflection, err, det)``, the three masks of shape ``(...)``
    disjoint (a non-finite matrix is only ``non_finite``; a reflection is orthogonal within
    ``atol``), ``err = ||R^T R - I||_F`` and ``det`` computed in at least float32."""
    with torch.no_grad():
        n = R.shape[-1]
        work = torch.promote_types(R.dtype, torch.float32)  # det/matrix_norm need >= float32
        Rd = R.detach().to(work)
        eye = torch.eye(n, dtype=work, device=R.device)
        finite = torch.isfinite(Rd).all(-1).all(-1)
        Rs = torch.where(finite[..., None, None], Rd, eye)
        err = torch.linalg.matrix_norm(Rs.transpose(-1, -2) @ Rs - eye)
        det = torch.linalg.det(Rs)
        not_orth = finite & (err > atol)
        return ~finite, not_orth, finite & ~not_orth & (det < 0), err, det


def _check_square(K: torch.Tensor, fn: str) -> int:
    if K.dim() < 2 or K.shape[-1] != K.shape[-2]:
        raise ValueError(f"{fn} expects a tensor of shape (..., n, n), got {tuple(K.shape)}")
    return K.shape[-1]


def _first_index(mask: torch.Tensor) -> tuple[int, ...]:
    return tuple(int(i) for i in torch.nonzero(mask)[0].tolist())


def check_rotation(R: torch.Tensor, name: str = "R", atol: float | None = None) -> None:
    """Raise ``ValueError`` unless every matrix of ``R (..., n, n)`` is a rotation.

    Checks, per matrix: all entries finite; ``||R^T R - I||_F <= atol``; ``det R > 0``.
    ``atol`` defaults to ``get_eps("rotation", R.dtype)``. The message names ``name``, the
    number of bad matrices and, for each defect found, the first offending batch index tuple
    (``()`` for an unbatched matrix) with the defect value. Synchronizes with the device
    (explicit validation, keep it out of hot paths). Returns ``None``. On the ``meta`` device
    (no values) only the type and shape are checked.
    """
    check_float_tensor(R, "check_rotation", name)
    _check_square(R, "check_rotation")
    if R.device.type == "meta":
        return
    if atol is None:
        atol = get_eps("rotation", R.dtype)
    with torch.no_grad():
        bad_fin, bad_orth, bad_det, err, det = rotation_defects(R, atol)
        bad = bad_fin | bad_orth | bad_det
        if not bool(bad.any()):
            return
        msgs = []
        if bool(bad_fin.any()):
            i = _first_index(bad_fin)
            msgs.append(f"non-finite entries (NaN/inf) at index {i}")
        if bool(bad_orth.any()):
            i = _first_index(bad_orth)
            msgs.append(
                f"not orthogonal at index {i}: ||R^T R - I||_F = {float(err[i]):.3e} > atol {atol:.1e}"
            )
        if bool(bad_det.any()):
            i = _first_index(bad_det)
            msgs.append(f"det = {float(det[i]):.6f} (a reflection, det -1) at index {i}")
        raise ValueError(
            f"{name} (shape {tuple(R.shape)}): {int(bad.sum())} of {bad.numel()} matrices are not "
            f"rotations; " + "; ".join(msgs)
        )
