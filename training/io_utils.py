"""File helpers for training commands: output-dir checks, atomic writes, checkpoints, RNG state.

Every file is written atomically: the bytes go to a temporary file in the *same* directory,
which is flushed, fsync'ed and then moved over the target with ``os.replace`` (atomic on POSIX
and Windows for paths on one file system). A crash mid-write therefore leaves either the old
file or the new one, never a truncated one; the last good checkpoint survives a failing run.
"""
from __future__ import annotations

import io
import json
import os
import random
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

__all__ = [
    "OutputDirError",
    "check_output_dir",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "atomic_savez",
    "save_checkpoint",
    "load_checkpoint",
    "get_rng_state",
    "set_rng_state",
]


class OutputDirError(OSError):
    """The output directory cannot be created or written (raised before any computation)."""


def check_output_dir(path) -> Path:
    """Create ``path`` if needed and check that files can be created, written and replaced in it.

    Raises:
        OutputDirError: naming the path, when it is a file, cannot be created, or is not writable.
    """
    p = Path(path).expanduser()
    if p.exists() and not p.is_dir():
        raise OutputDirError(f"output_dir {str(p)!r} exists and is not a directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputDirError(f"cannot create output_dir {str(p)!r}: {exc.strerror or exc}") from exc
    try:
        atomic_write_bytes(p / ".write_test", b"ok")
        (p / ".write_test").unlink()
    except OSError as exc:
        raise OutputDirError(f"output_dir {str(p)!r} is not writable: {exc.strerror or exc}") from exc
    return p


def atomic_write(path, writer: Callable[[Any], None], mode: str = "wb") -> Path:
    """Write a file atomically: ``writer(fileobj)`` fills a temp file that replaces ``path``.

    The temporary file lives in ``path``'s directory (so ``os.replace`` is atomic) and is
    removed if ``writer`` raises.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; use the usual permissions
        with os.fdopen(fd, mode) as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path, data: bytes) -> Path:
    """Atomically write ``data`` to ``path``."""
    return atomic_write(path, lambda f: f.write(data), "wb")


def atomic_write_text(path, text: str) -> Path:
    """Atomically write UTF-8 ``text`` to ``path``."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path, obj) -> Path:
    """Atomically write ``obj`` as indented JSON (NaN/inf are written as ``null``)."""
    return atomic_write_text(path, json.dumps(_json_safe(obj), indent=2, allow_nan=False) + "\n")


def _json_safe(obj):
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if torch.is_tensor(obj):
        return _json_safe(obj.detach().cpu().tolist())
    if isinstance(obj, np.ndarray):
        return _json_safe(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        x = float(obj)
        return x if np.isfinite(x) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj


def atomic_savez(path, **arrays) -> Path:
    """Atomically write an uncompressed ``.npz`` of numpy arrays (``np.savez`` semantics)."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def save_checkpoint(path, state: dict) -> Path:
    """Atomically ``torch.save`` a checkpoint dict to ``path``."""
    buf = io.BytesIO()
    torch.save(state, buf)
    return atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path, map_location="cpu") -> dict:
    """Load a checkpoint written by :func:`save_checkpoint`.

    Raises:
        FileNotFoundError: naming the path.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {str(path)!r}")
    return torch.load(path, map_location=map_location, weights_only=False)


def get_rng_state() -> dict:
    """RNG states of python ``random``, numpy's global generator and torch (CPU, and CUDA if used)."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore states saved by :func:`get_rng_state`."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
