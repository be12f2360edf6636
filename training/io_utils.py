"""File helpers for training commands: output-dir checks and lock, atomic writes, checkpoints, RNG state.

Every file is written atomically: the bytes go to a temporary file in the *same* directory,
which is flushed, fsync'ed and then moved over the target with ``os.replace`` (atomic on POSIX
and Windows for paths on one file system). A crash mid-write therefore leaves either the old
file or the new one, never a truncated one; the last good checkpoint survives a failing run.
The final outputs of a run are first written into a staging folder (:func:`staged_outputs`) and
moved in only when all of them exist, so a run stopped by an error adds no partial output.

One run at a time per output directory (:func:`lock_output_dir`): two runs writing into one
folder would mix their files (a checkpoint of one mesh beside the frames of another).
:func:`output_dir_for_run` adds that a run failing on its input leaves no directory behind.

A job's errors reach the user as one message, not a traceback (:func:`report_errors`), unless
``HYDRA_FULL_ERROR=1`` or the job's ``debug`` flag asks for the traceback.

Checkpoints hold only tensors and plain containers (dict, list, tuple, str, int, float, bool,
None) and are loaded with ``torch.load(weights_only=True)``: loading one never runs code from the
file, and a corrupted or foreign file is reported with its path (:class:`CheckpointError`).
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import random
import shutil
import socket
import sys
import tempfile
import time
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

__all__ = [
    "OutputDirError",
    "OutputDirLockedError",
    "output_dir_for_run",
    "remove_empty_dirs",
    "hydra_output_dir",
    "full_errors_wanted",
    "report_errors",
    "StaleLockWarning",
    "CheckpointError",
    "check_output_dir",
    "lock_output_dir",
    "staged_outputs",
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
    """Create ``path`` if needed and check that files can be created and written in it.

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
    try:  # a unique name: two runs checking one folder at once must not delete each other's probe
        with tempfile.NamedTemporaryFile(dir=p, prefix=".write_test.") as f:
            f.write(b"ok")
            f.flush()
    except OSError as exc:
        raise OutputDirError(f"output_dir {str(p)!r} is not writable: {exc.strerror or exc}") from exc
    return p


class OutputDirLockedError(OutputDirError):
    """Another running process holds the output directory's lock (the message names it)."""


class StaleLockWarning(UserWarning):
    """A lock file left by a run that is no longer running was taken over."""


LOCK_NAME = ".lock"


def _describe_holder(holder: dict) -> str:
    if not holder:
        return "holder unknown (empty lock file)"
    return (f"pid {holder.get('pid', '?')} on host {holder.get('host', '?')} since {holder.get('time', '?')}, "
            f"command {holder.get('argv', '?')!r}")


def _pid_alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, ValueError, TypeError, OverflowError):
        return True  # PermissionError: it exists under another user; ValueError: not a pid, assume held
    return True


def _holder_info() -> bytes:
    return json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                       "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "argv": " ".join(sys.argv)[:300]}).encode()


def _parse_holder(data: bytes) -> dict:
    try:
        holder = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return {}
    return holder if isinstance(holder, dict) else {}


def _acquire_flock(lock: Path) -> int:
    """``fcntl.flock`` on ``lock``: exclusive, released by the kernel when the process dies."""
    import fcntl

    for _ in range(8):
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            holder = _parse_holder(lock.read_bytes()) if lock.exists() else {}
            raise OutputDirLockedError(
                f"output_dir {str(lock.parent)!r} is in use by another run ({_describe_holder(holder)}); "
                f"wait for it to finish or choose another output_dir=...") from None
        except OSError as exc:  # e.g. ENOLCK: a network file system without locks
            os.close(fd)
            raise OutputDirError(f"output_dir {str(lock.parent)!r} cannot be locked ({exc.strerror or exc}); "
                                 f"use an output_dir on a local file system") from exc
        try:  # the previous holder may have unlinked the file between our open() and flock()
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        previous = _parse_holder(os.pread(fd, 4096, 0))
        if previous:  # left by a run that died without releasing (SIGKILL, power loss)
            host_ok = previous.get("host") == socket.gethostname()
            state = ("not running" if host_ok and not _pid_alive(previous.get("pid")) else
                     "no longer holding the lock")
            warnings.warn(f"output_dir {str(lock.parent)!r}: taking over the stale lock of "
                          f"{_describe_holder(previous)} ({state})", StaleLockWarning, stacklevel=4)
        os.ftruncate(fd, 0)
        os.pwrite(fd, _holder_info(), 0)
        return fd
    raise OutputDirLockedError(f"output_dir {str(lock.parent)!r}: could not take its lock {str(lock)!r} "
                               f"(other runs keep replacing it); choose another output_dir=...")


def _acquire_exclusive(lock: Path) -> int:
    """Without ``fcntl`` (Windows): ``O_CREAT | O_EXCL``; a lock left by a crash must be deleted by hand."""
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        holder = _parse_holder(lock.read_bytes())
        raise OutputDirLockedError(
            f"output_dir {str(lock.parent)!r} is in use by another run ({_describe_holder(holder)}); wait for it "
            f"to finish or choose another output_dir=... (if that run no longer exists, delete {str(lock)!r})"
        ) from None
    os.write(fd, _holder_info())
    return fd


@contextlib.contextmanager
def lock_output_dir(path):
    """Hold ``path/.lock`` for the duration of the ``with`` block: one run per output directory.

    The lock file holds the holder's pid, host, start time and command line (named in the error
    a second run gets). With ``fcntl`` (POSIX) the lock is an ``flock``, which the kernel drops
    when the holder dies; a lock file left that way is taken over with a :class:`StaleLockWarning`.
    The file is removed on exit, also when the block raises.

    Raises:
        OutputDirLockedError: naming the directory and the holder, when another run holds it.
    """
    lock = Path(path) / LOCK_NAME
    try:
        import fcntl  # noqa: F401
    except ImportError:
        fd = _acquire_exclusive(lock)
    else:
        fd = _acquire_flock(lock)
    try:
        yield lock
    finally:
        try:
            os.unlink(lock)  # before closing: a waiting run then finds no file or a fresh one
        except FileNotFoundError:
            pass
        os.close(fd)


@contextlib.contextmanager
def output_dir_for_run(path):
    """Create, check and lock ``path`` for one run (:func:`check_output_dir`,
    :func:`lock_output_dir`); yield it. If the block raises, the directories this call created
    (``path`` and any missing parents) are removed again where they are empty, so a run that
    fails on its input leaves no empty output directory behind; a directory that existed, or
    holds files, is kept."""
    p = Path(path).expanduser()
    created = []
    q = p.absolute()
    while not q.exists():
        created.append(q)
        if q.parent == q:
            break
        q = q.parent
    out = check_output_dir(p)
    try:
        with lock_output_dir(out):
            yield out
    except BaseException:
        remove_empty_dirs(created)  # deepest first
        raise


def remove_empty_dirs(dirs) -> None:
    """``rmdir`` each of ``dirs`` in order (deepest first), stopping at the first that is not
    empty (or cannot be removed): what a failed run created and left empty goes again."""
    for d in dirs:
        try:
            Path(d).rmdir()
        except OSError:
            break


@contextlib.contextmanager
def hydra_output_dir(cfg):
    """A job's command line run: with ``cfg.output_dir`` null, set it to Hydra's run directory
    (``outputs/<job>/<date>/<time>``, which Hydra created); if the block raises, the directories
    it made below the working directory are removed again where they are empty, so a run that
    fails on its input leaves no empty output directory behind. With ``output_dir`` given, Hydra
    created nothing (:func:`training.schema.run_dir`) and the block runs as is."""
    created = []
    if cfg.output_dir is None:
        from hydra.core.hydra_config import HydraConfig

        run_dir = Path(HydraConfig.get().runtime.output_dir)
        cfg.output_dir = str(run_dir)
        cwd = Path.cwd().resolve()
        created = [d for d in (run_dir, *run_dir.parents) if cwd in d.resolve().parents]
    try:
        yield cfg.output_dir
    except BaseException:
        remove_empty_dirs(created)  # deepest first
        raise


def full_errors_wanted(debug: bool = False) -> bool:
    """Whether a job shows its errors' tracebacks: ``debug`` or ``HYDRA_FULL_ERROR=1``."""
    return bool(debug) or os.environ.get("HYDRA_FULL_ERROR") == "1"


@contextlib.contextmanager
def report_errors(job: str, *, debug: bool = False, how: str = "HYDRA_FULL_ERROR=1"):
    """Around a job's body: an exception is printed to stderr as ``[job] error: message`` with its
    class and how to see the traceback (``how``), and the process exits with status 1; with
    ``debug`` or ``HYDRA_FULL_ERROR=1`` (:func:`full_errors_wanted`) it propagates (Hydra prints
    the traceback). ``KeyboardInterrupt`` and ``SystemExit`` always propagate."""
    try:
        yield
    except Exception as exc:  # noqa: BLE001 - every error of a job is reported the same way
        if full_errors_wanted(debug):
            raise
        msg = str(exc).strip() or repr(exc)
        if isinstance(exc, KeyError) and msg.startswith(("'", '"')):  # KeyError quotes its message
            msg = msg[1:-1]
        print(f"[{job}] error: {msg}", file=sys.stderr)
        print(f"[{job}] ({type(exc).__name__}; for the traceback run again with {how})", file=sys.stderr)
        raise SystemExit(1) from None


@contextlib.contextmanager
def staged_outputs(out, last=("metrics.json",)):
    """Yield a staging folder inside ``out``; on success move its files into ``out``.

    Writers (including ones that are not atomic themselves, e.g. meshio or matplotlib) write into
    the staging folder; only when the ``with`` block ends normally is each file fsync'ed and moved
    over its target with ``os.replace`` (files named in ``last`` last, so ``metrics.json`` appears
    only after the rest). If the block raises, the staging folder is deleted: no partial output.
    """
    out = Path(out)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        yield stage
        for name in sorted(os.listdir(stage), key=lambda n: (n in last, n)):
            src = stage / name
            if src.is_file():
                with open(src, "rb") as f:
                    os.fsync(f.fileno())
            os.replace(src, out / name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


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


class CheckpointError(ValueError):
    """A checkpoint that is corrupted, not loadable without running code, or of another configuration."""


_SCALARS = (str, int, float, bool, type(None))


def _plain(obj, where: str):
    """``obj`` with numpy scalars made Python scalars; ``TypeError`` naming ``where`` for anything
    that ``torch.load(weights_only=True)`` would refuse (so a bad checkpoint fails when written)."""
    if isinstance(obj, dict):
        items = {}
        for k, v in obj.items():
            if type(k) not in (str, int):
                raise TypeError(f"checkpoint key {where}[{k!r}] is a {type(k).__name__}; keys must be str or int")
            items[k] = _plain(v, f"{where}[{k!r}]")
        return OrderedDict(items) if isinstance(obj, OrderedDict) else items
    if type(obj) in (list, tuple):
        return type(obj)(_plain(v, f"{where}[{i}]") for i, v in enumerate(obj))
    if torch.is_tensor(obj) or type(obj) in _SCALARS:
        return obj
    if isinstance(obj, np.generic) and obj.ndim == 0:
        return obj.item()
    raise TypeError(f"checkpoint entry {where} is a {type(obj).__module__}.{type(obj).__name__}; a checkpoint "
                    f"holds only tensors, dict/list/tuple and str/int/float/bool/None (convert it first)")


def save_checkpoint(path, state: dict) -> Path:
    """Atomically ``torch.save`` a checkpoint dict of tensors and plain containers to ``path``.

    Raises:
        TypeError: naming the entry that :func:`load_checkpoint` could not load safely (e.g. a
            numpy array or an arbitrary object), before anything is written.
    """
    state = _plain(state, "state")
    buf = io.BytesIO()
    torch.save(state, buf)
    return atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path, map_location="cpu", fingerprint: str | None = None, required=()) -> dict:
    """Load a checkpoint written by :func:`save_checkpoint`, never running code from the file.

    Args:
        path: the checkpoint file.
        map_location: as in ``torch.load``.
        fingerprint: when given, ``state["fingerprint"]`` must equal it (the configuration the
            checkpoint was written for).
        required: keys the state must have.

    Raises:
        FileNotFoundError: naming the path.
        CheckpointError: naming the path and what to do, for a file that is not a zip/pickle
            checkpoint (random bytes, truncated), that holds objects other than tensors and plain
            containers (``weights_only=True`` refuses them: a pickled ``os.system`` is not run),
            that lacks a ``required`` key, or whose fingerprint differs.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {str(path)!r}")
    fix = "delete it, or run without resume=true (or with another output_dir)"
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 -- torch raises RuntimeError, EOFError, UnpicklingError, UnicodeDecodeError, ...
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        # torch's message is long; keep its informative line (the refused global or opcode)
        detail = next((ln for ln in lines if "GLOBAL" in ln or "Unsupported" in ln), lines[0] if lines else "")
        detail = f"{type(exc).__name__}: {detail}"
        if "GLOBAL" in str(exc):  # a pickled callable, class or function: refused, never called
            raise CheckpointError(f"checkpoint {str(path)!r} holds objects other than tensors and plain "
                                  f"containers and was not loaded (loading it could run code from the file); "
                                  f"it was not written by this command: {fix} ({detail})") from None
        raise CheckpointError(f"checkpoint {str(path)!r} cannot be read: it is corrupted, truncated or not a "
                              f"checkpoint ({detail}); {fix}") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {str(path)!r} holds a {type(state).__name__}, not a checkpoint dict; {fix}")
    missing = [k for k in required if k not in state]
    if missing:
        raise CheckpointError(f"checkpoint {str(path)!r} lacks {missing} (not written by this command or by an "
                              f"older version); {fix}")
    if fingerprint is not None and state.get("fingerprint") != fingerprint:
        raise CheckpointError(f"checkpoint {str(path)!r} was written for another mesh/method/optimizer/weights "
                              f"configuration; refusing to resume: use the same configuration, or {fix}")
    return state


def get_rng_state() -> dict:
    """RNG states of python ``random``, numpy's global generator and torch (CPU, and CUDA if used).

    Only tensors and plain containers (numpy's key array as an int64 tensor), so that the state
    goes into a ``weights_only`` checkpoint.
    """
    npst = np.random.get_state(legacy=False)
    npst = {**npst, "state": {**npst["state"], "key": torch.from_numpy(npst["state"]["key"].astype(np.int64))}}
    state = {"python": random.getstate(), "numpy": npst, "torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore states saved by :func:`get_rng_state`."""
    random.setstate(state["python"])
    npst = state["numpy"]
    key = np.asarray(npst["state"]["key"].cpu().numpy(), dtype=np.uint32)
    np.random.set_state({**npst, "state": {**npst["state"], "key": key}})
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
