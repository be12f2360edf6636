"""torchconn.ops.native: build once, cache, fall back with one clear warning."""
import warnings

import pytest
import torch

from torchconn.ops import native
from torchconn.ops.backend import can_use_compiled


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """An empty cache folder and no loaded libraries (restored afterwards)."""
    monkeypatch.setenv("TORCHCONN_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(native, "_LIBS", {})
    monkeypatch.setattr(native, "_WARNED", set())
    return tmp_path / "cache"


def test_builds_once_into_the_cache(fresh):
    if native._compiler() is None:
        pytest.skip("no C compiler on this machine")
    lib = native.library("curvature")
    assert lib is not None and hasattr(lib, "curv_fwd_f32") and hasattr(lib, "curv_fwd_f64")
    built = sorted(fresh.glob("curvature-*.so"))
    assert len(built) == 1 and not list(fresh.glob("*.so.tmp*"))
    mtime = built[0].stat().st_mtime_ns
    native._LIBS.clear()  # a new process: loads the cached library, no rebuild
    assert native.library("curvature") is not None
    assert built[0].stat().st_mtime_ns == mtime and sorted(fresh.glob("curvature-*.so")) == built


def test_registered_source_outside_csrc_builds_with_the_pool(fresh, monkeypatch, tmp_path):
    """A kernel package outside ops/ registers its C file (frames/kernels does): it is built like
    the core sources, finds ``pool.c`` on the include path and gets the pool when loaded; a name
    that is taken is refused."""
    if native._compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setattr(native, "_SOURCES", dict(native._SOURCES))
    assert native.library("plus_one") is None and "plus_one" not in native._LIBS  # unknown: not cached
    src = tmp_path / "src" / "plus_one.c"
    src.parent.mkdir()
    src.write_text('#define TC_POOL_CLIENT\n#include "pool.c"\nint plus_one(int x) { return x + 1; }\n')
    native.register_source("plus_one", src)
    native.register_source("plus_one", src)  # the same file again: a no-op
    lib = native.library("plus_one")
    assert lib is not None and lib.plus_one(41) == 42 and hasattr(lib, "tc_pool_attach")
    assert b"tc_parallel" in native._source_bytes(src)  # the key covers pool.c, found in CSRC
    with pytest.raises(ValueError, match="taken"):
        native.register_source("plus_one", tmp_path / "other.c")
    with pytest.raises(ValueError, match="taken"):
        native.register_source("so3", src)  # a core source's name
    import torchconn.frames.kernels as fk  # the frame kernels' sources are registered on import

    assert native._source("frame_loss") == fk.CSRC / "frame_loss.c"


def test_failed_build_warns_once_and_falls_back(fresh, monkeypatch):
    monkeypatch.setenv("CC", "false")  # a "compiler" that always fails
    with pytest.warns(RuntimeWarning, match="building curvature.c failed"):
        assert native.library("curvature") is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert native.library("curvature") is None  # cached decision, no second warning
    x = torch.zeros(3, 3, dtype=torch.float64)
    assert not can_use_compiled("curvature", x)


def test_missing_compiler(fresh, monkeypatch):
    monkeypatch.setattr(native, "_compiler", lambda: None)
    with pytest.warns(RuntimeWarning, match="no C compiler"):
        assert native.library("curvature") is None


def test_unwritable_cache_falls_back(fresh, monkeypatch, tmp_path):
    if native._compiler() is None:
        pytest.skip("no C compiler on this machine")
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("TORCHCONN_CACHE", str(blocker / "sub"))
    with pytest.warns(RuntimeWarning, match="cannot build"):
        assert native.library("curvature") is None


def test_can_use_compiled_checks_device_and_dtype():
    import torchconn.ops

    if native.library("curvature") is None:
        pytest.skip("no C compiler on this machine")
    f64, f32 = torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float32)
    with torchconn.ops.compiled(True):
        assert can_use_compiled("curvature", f64, f64) and can_use_compiled("curvature", f32)
        assert not can_use_compiled("curvature", f64, f32)  # mixed dtypes
        assert not can_use_compiled("curvature", torch.zeros(2, dtype=torch.float16))
        assert not can_use_compiled("curvature", torch.zeros(2, device="meta"))
        assert not can_use_compiled("curvature")
    with pytest.raises(ValueError, match="contiguous"):
        native.ptr(torch.zeros(3, 3).t())


def test_torch_compile_traces_the_torch_path():
    """Under torch.compile (fake tensors, no data pointers) the callers record their torch code."""
    from torchconn import so3
    from torchconn.frames.loss import FrameFieldLoss
    from torchconn import io

    mesh = io.box(1)
    loss = FrameFieldLoss(mesh, {"smooth": 1.0, "tie": 1.0, "flat": 1.0, "torsion": 1.0})
    g = torch.Generator().manual_seed(0)
    w = 0.2 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=torch.float64)
    phi = 0.2 * torch.randn(mesh.n_vertices, 3, generator=g, dtype=torch.float64)

    def f(w, phi):
        return loss(so3.exp(w), so3.exp(phi))["total"]

    compiled = torch.compile(f, backend="eager", fullgraph=False)
    assert abs(float(compiled(w, phi)) - float(f(w, phi))) <= 1e-12


def test_declared_signature_rejects_wrong_calls():
    """argtypes make a caller that disagrees with the C signature fail in Python, not in C."""
    import ctypes

    if native.library("so3") is None:
        pytest.skip("no C compiler on this machine")
    fn = native.function("so3", "so3_exp_fwd_f64", [ctypes.c_void_p] * 2 + [ctypes.c_long, ctypes.c_int, ctypes.c_double])
    x = torch.zeros(1, 3, dtype=torch.float64)
    with pytest.raises(TypeError):
        fn(native.ptr(x), ctypes.c_long(1), ctypes.c_int(1), ctypes.c_double(1e-4))  # one pointer missing
    with pytest.raises(ctypes.ArgumentError):
        fn(native.ptr(x), 1.5, ctypes.c_long(1), ctypes.c_int(1), ctypes.c_double(1e-4))  # a float for a pointer
    out = torch.empty(1, 9, dtype=torch.float64)
    fn(native.ptr(x), native.ptr(out), 1, 1, 1e-4)
    assert torch.equal(out.reshape(3, 3), torch.eye(3, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="not available"):
        native._LIBS["nothing"] = None
        native.function("nothing", "f", [])


@pytest.mark.parametrize("shape", [(0, 3), (5, 3, 3), (native.HUGE_MIN_BYTES // 4 + 7,)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_is_an_ordinary_writable_tensor(shape, dtype):
    """Small, empty and huge-page-advised buffers: the shape and dtype asked, contiguous, on the
    CPU, every element writable (the advice changes how pages are backed, never the contents)."""
    t = native.empty(*shape, dtype=dtype)
    assert t.shape == shape and t.dtype == dtype and t.device.type == "cpu" and t.is_contiguous()
    t.fill_(3.0)
    assert bool((t == 3.0).all())


def test_cache_key_covers_included_sources(tmp_path):
    """A kernel file's key hashes the files it takes code from (``#include "..."``), each once
    (a self-include is not followed twice): editing so3.c rebuilds tet.c's library too."""
    a, b = tmp_path / "a.c", tmp_path / "b.c"
    a.write_text('#include "b.c"\n#include "a.c"\nint f(void) { return 1; }\n')
    b.write_text("int g(void) { return 2; }\n")
    before = native._source_bytes(a)
    assert b"int g(void)" in before and before.count(b"int f(void)") == 1
    b.write_text("int g(void) { return 3; }\n")
    assert native._source_bytes(a) != before
    assert b"so3_sqrt_fwd" in native._source_bytes(native.CSRC / "tet.c")


# ---------------------------------------------------------------- the kernels' thread pool


def _pool_workers() -> int:
    lib = native.library("pool")
    lib.tc_pool_workers.restype = __import__("ctypes").c_int
    return int(lib.tc_pool_workers())


def _exp_threads(w, nt):
    """so3_exp_fwd (compiled) of w (n, 3) with nt threads: R (n, 9)."""
    out = torch.empty(w.shape[0], 9, dtype=w.dtype)
    fn = native.function("so3", "so3_exp_fwd_f64", [__import__("ctypes").c_void_p] * 2
                         + [__import__("ctypes").c_long, __import__("ctypes").c_int, __import__("ctypes").c_double])
    fn(native.ptr(w), native.ptr(out), w.shape[0], nt, 1e-4)
    return out


def test_pool_runs_kernels_on_several_threads_with_the_same_results():
    """The kernel libraries get the pool (csrc/pool.c) when loaded: a loop with 4 threads
    creates workers and gives bitwise the one-thread values (cost ~0.1 s)."""
    if native._compiler() is None:
        pytest.skip("no C compiler on this machine")
    w = torch.randn(50_000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    one = _exp_threads(w, 1)
    assert torch.equal(_exp_threads(w, 4), one)
    assert _pool_workers() >= 1


def test_pool_from_two_python_threads_and_after_fork():
    """Two Python threads calling kernels at once (one runs its loop on its own thread), and a
    forked child (no workers survive a fork: the pool starts again) get the right values."""
    import os
    import threading

    if native._compiler() is None:
        pytest.skip("no C compiler on this machine")
    w = torch.randn(40_000, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ref = _exp_threads(w, 1)
    _exp_threads(w, 2)  # workers exist before the fork
    results = []
    ts = [threading.Thread(target=lambda: results.append(torch.equal(_exp_threads(w, 2), ref))) for _ in range(2)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert results == [True, True]
    ref_bytes = ref.numpy().tobytes()
    pid = os.fork()
    if pid == 0:  # child: exit status 0 iff the pooled loop is right
        ok = False
        try:  # compared in numpy: torch's own OpenMP regions hang in a forked child
            ok = _exp_threads(w, 2).numpy().tobytes() == ref_bytes
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
