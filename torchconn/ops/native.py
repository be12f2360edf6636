"""Loader of the compiled CPU kernels: C sources in ``torchconn/ops/csrc`` built once with the system compiler.

The fused torch kernels are limited by what eager torch can express: every 3x3 product over a
million edges is a separate pass over memory. The hottest loops (the frame-field loss, the
SO(3) maps) are therefore also written as plain C loops over elements, computing values *and*
their gradients in one sweep. They are compiled on first use with ``cc -O3 -march=native``
(no torch headers, no Python headers: the shared library takes raw pointers and is loaded with
:mod:`ctypes`; ``-fopenmp-simd`` honours the ``omp simd`` loop hints without an OpenMP
runtime), cached under ``$TORCHCONN_CACHE`` (default ``~/.cache/torchconn``) by a hash of the
source (with the files it includes), the compiler command and the CPU, and written
atomically (compiled to a temporary name, then renamed), so concurrent processes never load a
half-written library. ``$TORCHCONN_MARCH`` replaces ``native`` (``x86-64-v3``, for code that
runs on every AVX2 CPU, e.g. in a cache shared by different machines; ``none``: no ``-march``).

:func:`library` returns ``None`` (after one :class:`RuntimeWarning` naming the reason) when no
C compiler is found (``$CC``, ``cc``, ``gcc``, ``clang``) or the build fails; whether an op
uses a library at all is decided by :func:`torchconn.ops.backend.can_use_compiled` (the
global switch, devices and dtypes). The torch kernels are the reference and the fallback.

Threads: the kernels' parallel loops run on one thread pool of their own, ``csrc/pool.c``
(built like the kernels and handed to every kernel library when it is loaded), with up to
``torch.get_num_threads()`` threads per call (the caller included), so ``torch.set_num_threads``
governs both. Unlike OpenMP's fork-join, a loop never waits for a thread that has not
started: tasks are claimed from a shared counter by the caller too, and waiting threads sleep
after a short spin (a core held by another process costs a loop at most the tasks already
running there; see ``pool.c`` and ``benchmarks/under_load.py``). No OpenMP runtime is loaded
by the kernels, so none competes with torch's.

Outputs: the kernels write into tensors from :func:`empty`, which advises the kernel to back
large ones with transparent huge pages (see there).
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
from pathlib import Path

import torch

__all__ = ["library", "declare", "register_source", "CFunction", "ptr", "empty", "CSRC"]

#: Folder of the C sources (of the core kernels; and of ``pool.c``, which every kernel includes).
CSRC = Path(__file__).resolve().parent / "csrc"
#: Kernel libraries whose source lies outside :data:`CSRC` (:func:`register_source`): name -> file.
_SOURCES: dict[str, Path] = {}
_BASE_FLAGS = ["-O3", "-fopenmp-simd", "-pthread", "-fPIC", "-shared", "-std=c99", "-fno-math-errno",
               "-ffp-contract=off"]
_LOCK = threading.RLock()  # library() of a kernel loads the pool library inside it
_LIBS: dict[str, ctypes.CDLL | None] = {}
_WARNED: set[str] = set()


def _compiler() -> str | None:
    """``$CC`` when it is set (and only it: a named compiler that is missing is not replaced by
    another one), else the first of ``cc``, ``gcc``, ``clang`` on the ``PATH``."""
    cc = os.environ.get("CC", "").strip()
    if cc:
        return shutil.which(cc)
    for cand in ("cc", "gcc", "clang"):
        if shutil.which(cand):
            return shutil.which(cand)
    return None


def _flags() -> list[str]:
    """The compiler flags: the fixed ones and ``-march=`` from ``$TORCHCONN_MARCH`` (default
    ``native``; ``none`` leaves the compiler's default target)."""
    march = os.environ.get("TORCHCONN_MARCH", "").strip() or "native"
    return _BASE_FLAGS + ([] if march.lower() == "none" else [f"-march={march}"])


def _cpu_key() -> str:
    """CPU model + flags (``-march=native`` code must not run on another CPU sharing the cache)."""
    info = platform.machine() + platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags"))]
        info += "".join(sorted(set(lines)))
    except OSError:
        pass
    return info


def _cache_dir() -> Path:
    root = os.environ.get("TORCHCONN_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "torchconn"


def register_source(name: str, path: Path) -> None:
    """Build the kernel library ``name`` from the C file ``path`` (a kernel package outside ``ops/``,
    e.g. the frame-field kernels of :mod:`torchconn.frames.kernels`).

    The file is compiled like the sources of :data:`CSRC`, with :data:`CSRC` on the include path
    (``#include "pool.c"`` finds the thread pool); the cache key covers the file and what it
    includes. Registering another file under a name already taken raises ``ValueError``.
    Nothing is built here (the library is built at its first use, :func:`library`).
    """
    path = Path(path).resolve()
    if (CSRC / f"{name}.c").exists() or _SOURCES.get(name, path) != path:
        raise ValueError(f"torchconn.ops.native: the kernel library name {name!r} is taken "
                         f"({_SOURCES.get(name, CSRC / f'{name}.c')})")
    _SOURCES[name] = path


def _source(name: str) -> Path:
    """The C file of the kernel library ``name``."""
    return _SOURCES.get(name, CSRC / f"{name}.c")


def _warn_once(name: str, msg: str) -> None:
    if name not in _WARNED:
        _WARNED.add(name)
        warnings.warn(f"torchconn.ops.native: {_source(name).parent.name}/{name}.c: {msg}; using the torch kernels",
                      RuntimeWarning, stacklevel=3)


_QUOTED_INCLUDE = re.compile(rb'^\s*#\s*include\s+"([^"]+)"', re.M)


def _source_bytes(src: Path) -> bytes:
    """``src`` and, recursively, every file it includes with ``#include "..."`` (next to it, else
    in :data:`CSRC`, the compiler's include path), each once: the cache key then covers code one
    kernel file takes from another (``tet.c`` includes the element kernels of ``so3.c``)."""
    seen: list[Path] = []

    def visit(path: Path) -> None:
        if path in seen or not path.exists():
            return
        seen.append(path)
        for inc in _QUOTED_INCLUDE.findall(path.read_bytes()):
            near = (path.parent / inc.decode()).resolve()
            visit(near if near.exists() else (CSRC / inc.decode()).resolve())

    visit(src.resolve())
    return b"".join(p.name.encode() + b"\0" + p.read_bytes() for p in seen)


def _build(name: str) -> ctypes.CDLL | None:
    src = _source(name)
    cc = _compiler()
    if cc is None:
        cc_env = os.environ.get("CC", "").strip()
        _warn_once(name, f"no C compiler found ($CC={cc_env!r} not found)" if cc_env
                   else "no C compiler found ($CC, cc, gcc, clang)")
        return None
    code = _source_bytes(src)
    flags = _flags()
    key = hashlib.sha256(code + cc.encode() + " ".join(flags).encode() + _cpu_key().encode()).hexdigest()[:16]
    out_dir = _cache_dir()
    lib_path = out_dir / f"{name}-{key}.so"
    if not lib_path.exists():
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(suffix=".so", dir=out_dir)
            os.close(fd)
            proc = subprocess.run([cc, *flags, f"-I{CSRC}", str(src), "-o", tmp, "-lm"], capture_output=True,
                                  text=True)
            if proc.returncode != 0:
                os.unlink(tmp)
                _warn_once(name, f"building {src.name} failed ({cc} exit {proc.returncode}): "
                                 f"{proc.stderr.strip()[-500:]}")
                return None
            os.replace(tmp, lib_path)  # atomic: a concurrent build of the same key is identical
        except OSError as exc:
            _warn_once(name, f"cannot build {src.name} in {out_dir}: {exc}")
            return None
    try:
        return ctypes.CDLL(str(lib_path))
    except OSError as exc:
        _warn_once(name, f"cannot load {lib_path}: {exc}")
        return None


def library(name: str) -> ctypes.CDLL | None:
    """The compiled ``csrc/<name>.c`` (or the file :func:`register_source` gave for ``name``; built
    on first use, cached), or ``None`` (see module doc).

    A kernel library that includes the client part of ``pool.c`` gets the thread pool
    (``library("pool")``) when it is loaded; without it (the pool failed to build) its loops
    run on the calling thread.
    """
    with _LOCK:
        if name not in _LIBS:
            if not _source(name).exists():
                # not (yet) a kernel library: a package outside ops/ registers its source when it is
                # imported (register_source); nothing is cached, so a later call after that builds it
                return None
            lib = _build(name)
            if lib is not None and name != "pool" and hasattr(lib, "tc_pool_attach"):
                pool = library("pool")
                if pool is not None:
                    lib.tc_pool_attach.argtypes, lib.tc_pool_attach.restype = [ctypes.c_void_p], None
                    lib.tc_pool_attach(ctypes.cast(pool.tc_pool_run, ctypes.c_void_p))
            _LIBS[name] = lib
        return _LIBS[name]


def function(name: str, symbol: str, argtypes: list, restype=None):
    """The C function ``symbol`` of ``csrc/<name>.c`` with its signature set (what
    :class:`CFunction` resolves on its first call).

    Not public API (not in ``__all__``): op modules declare their symbols once with
    :func:`declare`; the tests call this to reach a C function directly.
    With ``argtypes`` set, ctypes checks the number and kinds of the arguments of every call.
    The library must be available (see :func:`library`).
    """
    lib = library(name)
    if lib is None:
        raise RuntimeError(f"torchconn.ops.native: {_source(name)} is not available (see the warning above)")
    fn = getattr(lib, symbol)
    fn.argtypes, fn.restype = argtypes, restype
    return fn


def ptr(t: torch.Tensor) -> ctypes.c_void_p:
    """Raw data pointer of a contiguous tensor (the caller keeps the tensor alive)."""
    if not t.is_contiguous():
        raise ValueError("native kernels need contiguous tensors")
    return ctypes.c_void_p(t.data_ptr())


#: Buffers of at least this many bytes get ``madvise(MADV_HUGEPAGE)`` in :func:`empty`.
HUGE_MIN_BYTES = 4 << 20
_HUGE_PAGE = 2 << 20
_MADV_HUGEPAGE = 14  # <linux/mman.h>


def _madvise():
    """libc's ``madvise`` with its signature set, or ``None`` off Linux (or if it is missing)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int], ctypes.c_int
    return fn


_MADVISE = _madvise()


def empty(*shape, dtype: torch.dtype) -> torch.Tensor:
    """An uninitialised contiguous CPU tensor of ``shape`` for a kernel that writes every element.

    A buffer of ``HUGE_MIN_BYTES`` or more is fresh memory from the OS (glibc maps large
    blocks anew at each allocation), so the kernel that fills it first pays one page fault per
    4 KiB page. With transparent huge pages in ``madvise`` mode (the usual default) the 2 MiB
    aligned interior of the buffer is advised ``MADV_HUGEPAGE`` before the kernel touches it:
    one fault per 2 MiB instead. Measured on a 2-core KVM guest: a 72 MB buffer's first fill
    28 ms -> 7 ms, and the random gathers of the kernels that later read it miss the TLB less.
    Only advice: a refusal (``THP`` ``never``, another OS) leaves an ordinary tensor, and the
    memory used is the same.
    """
    t = torch.empty(*shape, dtype=dtype)
    n_bytes = t.numel() * t.element_size()
    if _MADVISE is not None and n_bytes >= HUGE_MIN_BYTES:
        start = (t.data_ptr() + _HUGE_PAGE - 1) & ~(_HUGE_PAGE - 1)
        end = (t.data_ptr() + n_bytes) & ~(_HUGE_PAGE - 1)
        if end > start:
            _MADVISE(start, end - start, _MADV_HUGEPAGE)
    return t


class CFunction:
    """A C function of ``csrc/<lib>.c`` whose signature is declared once, where it is defined.

    Op modules declare each symbol they call at import time (nothing is built then); the
    library is built and the symbol resolved, with ``argtypes``/``restype`` set once, on the
    first call. Calling checks the number and kinds of the arguments (``ctypes.ArgumentError``
    on a mismatch).

    >>> _EXP = {torch.float32: declare("so3", "so3_exp_fwd_f32", [c_void_p, c_void_p, c_long])}
    """

    __slots__ = ("lib", "symbol", "argtypes", "restype", "_fn")

    def __init__(self, lib: str, symbol: str, argtypes: list, restype=None):
        self.lib, self.symbol, self.argtypes, self.restype = lib, symbol, list(argtypes), restype
        self._fn = None

    def __call__(self, *args):
        fn = self._fn
        if fn is None:
            fn = self._fn = function(self.lib, self.symbol, self.argtypes, self.restype)
        return fn(*args)

    def __repr__(self) -> str:
        return f"CFunction({self.lib}:{self.symbol})"


def declare(lib: str, symbol: str, argtypes: list, restype=None) -> CFunction:
    """Declare the C function ``symbol`` of ``csrc/<lib>.c`` (see :class:`CFunction`)."""
    return CFunction(lib, symbol, argtypes, restype)
