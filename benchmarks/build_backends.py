"""ctypes + ``cc`` against ``torch.utils.cpp_extension``: build time, call overhead, runtime.

    python -m benchmarks.build_backends [--n 1000000] [--threads 2] [--repeats 20]

Issue 11 asks to decide by measurement whether the C kernels stay built by the system compiler
at first use and loaded with :mod:`ctypes` (today's :mod:`torchconn.ops.native`), or move to a
``torch.utils.cpp_extension`` module (torch's own thread pool instead of a second OpenMP runtime,
``at::Tensor`` checks, dtype dispatch, an op registered with the dispatcher in C++).

Both variants run the *same* C source, ``ops/csrc/so3.c`` (the exp forward, float32 and
float64):

* **ctypes**: ``cc -O3 -fopenmp -march=native`` into a shared library, the loop parallelized by
  OpenMP inside C, called through a :class:`~torchconn.ops.native.CFunction`;
* **cpp_extension**: a C++ wrapper that includes ``so3.c`` (``extern "C"``), checks its
  ``at::Tensor`` argument, dispatches on the dtype and splits the elements with
  ``at::parallel_for`` (torch's intra-op pool; each chunk calls the C loop with one thread),
  registered as ``torchconn_bench::exp_fwd`` with ``TORCH_LIBRARY`` and called through
  ``torch.ops``.

Printed, side by side in one run: the first (cold) build time of each (cpp_extension needs
``ninja``; the row says so when it is missing), the per-call time on one element (the call
overhead: Python → kernel → output tensor), and the time of one call on ``--n`` elements with
``--threads`` threads. The public ``torchconn.ops.so3.exp`` (eager, no grad) is a third row for
reference. Every build goes to a fresh temporary directory (nothing cached is reused).
"""
from __future__ import annotations

import argparse
import ctypes
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from torchconn.ops import native, so3

SRC = native.CSRC / "so3.c"

_WRAPPER = r"""
#include <torch/extension.h>
#include <ATen/Parallel.h>
extern "C" {
#include "%(src)s"
}

static void run(const float* s, float* d, long n, double eps) { so3_exp_fwd_f32(s, d, n, 1, eps); }
static void run(const double* s, double* d, long n, double eps) { so3_exp_fwd_f64(s, d, n, 1, eps); }

static at::Tensor exp_fwd(const at::Tensor& w, double eps) {
  TORCH_CHECK(w.dim() >= 1 && w.size(-1) == 3, "exp_fwd expects (..., 3), got ", w.sizes());
  TORCH_CHECK(w.device().is_cpu(), "exp_fwd: CPU tensors only");
  auto wc = w.contiguous();
  auto sizes = w.sizes().vec();
  sizes.push_back(3);
  auto out = at::empty(sizes, w.options());
  const int64_t n = w.numel() / 3;
  AT_DISPATCH_FLOATING_TYPES(w.scalar_type(), "exp_fwd", [&] {
    const scalar_t* src = wc.data_ptr<scalar_t>();
    scalar_t* dst = out.data_ptr<scalar_t>();
    at::parallel_for(0, n, 16384, [&](int64_t b, int64_t e) {
      run(src + 3 * b, dst + 9 * b, (long)(e - b), eps);
    });
  });
  return out;
}

TORCH_LIBRARY(torchconn_bench, m) { m.def("exp_fwd(Tensor w, float eps) -> Tensor"); }
TORCH_LIBRARY_IMPL(torchconn_bench, CPU, m) { m.impl("exp_fwd", &exp_fwd); }
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {}
"""


def _median_time(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def build_ctypes(tmp: Path):
    """Cold build of ``so3.c`` exactly as :mod:`torchconn.ops.native` does: ``(seconds, CDLL)``."""
    cc = native._compiler()
    out = tmp / "so3_bench.so"
    t0 = time.perf_counter()
    subprocess.run([cc, *native._flags(), str(SRC), "-o", str(out), "-lm"], check=True, capture_output=True)
    secs = time.perf_counter() - t0
    return secs, ctypes.CDLL(str(out))


def build_cpp_extension(tmp: Path):
    """Cold build of the C++ wrapper: ``(seconds, callable)`` or ``(None, reason)``."""
    if shutil.which("ninja") is None:
        try:
            import ninja  # noqa: F401  (the PyPI package puts the binary on PATH of its venv)
        except ImportError:
            return None, "ninja is not installed (pip install ninja)"
    from torch.utils import cpp_extension

    src = tmp / "so3_ext.cpp"
    src.write_text(_WRAPPER % {"src": SRC.as_posix()})
    t0 = time.perf_counter()
    cpp_extension.load(name="torchconn_bench_so3", sources=[str(src)], build_directory=str(tmp),
                       extra_cflags=["-O3", "-march=native", "-fno-math-errno", "-fopenmp-simd"], verbose=False)
    secs = time.perf_counter() - t0
    return secs, torch.ops.torchconn_bench.exp_fwd


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    eps = {d: float(__import__("torchconn").tolerances.get_eps("small_angle", d))
           for d in (torch.float32, torch.float64)}

    with tempfile.TemporaryDirectory() as d1, tempfile.TemporaryDirectory() as d2:
        t_cc, lib = build_ctypes(Path(d1))
        t_ext, ext = build_cpp_extension(Path(d2))
        fns = {dt: native.CFunction("so3", f"so3_exp_fwd_{tag}",
                                    [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_long, ctypes.c_int,
                                     ctypes.c_double])
               for dt, tag in ((torch.float32, "f32"), (torch.float64, "f64"))}
        for dt, f in fns.items():  # bind to the freshly built library, not the cached one
            f._fn = getattr(lib, f.symbol)
            f._fn.argtypes, f._fn.restype = f.argtypes, None

        def via_ctypes(w):
            out = torch.empty(*w.shape, 3, dtype=w.dtype)
            fns[w.dtype](ctypes.c_void_p(w.data_ptr()), ctypes.c_void_p(out.data_ptr()),
                         ctypes.c_long(w.numel() // 3), ctypes.c_int(torch.get_num_threads()),
                         ctypes.c_double(eps[w.dtype]))
            return out

        print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, n = {args.n:,}")
        print(f"first build (cold): ctypes + cc {t_cc:.2f} s; cpp_extension "
              + (f"{t_ext:.2f} s" if t_ext is not None else f"not built: {ext}"))
        print("| dtype | variant | call on 1 element (µs) | call on n elements (ms) |")
        print("|---|---|---|---|")
        gen = torch.Generator().manual_seed(0)
        for dt in (torch.float32, torch.float64):
            one = torch.randn(1, 3, generator=gen, dtype=dt)
            big = torch.randn(args.n, 3, generator=gen, dtype=dt)
            variants = {"ctypes (OpenMP)": via_ctypes}
            if t_ext is not None:
                variants["cpp_extension (at::parallel_for)"] = lambda w, dt=dt: ext(w, eps[dt])
            variants["torchconn.ops.so3.exp (public)"] = so3.exp
            ref = via_ctypes(big)
            for name, fn in variants.items():
                err = (fn(big) - ref).abs().max().item()
                if err > 8 * torch.finfo(dt).eps:  # same C loop; vectorization/FMA may differ
                    raise SystemExit(f"{name} differs from ctypes by {err}")
                t1 = _median_time(lambda: fn(one), args.repeats * 50) * 1e6
                tn = _median_time(lambda: fn(big), args.repeats) * 1e3
                print(f"| {str(dt).split('.')[-1]} | {name} | {t1:.1f} | {tn:.2f} |")


if __name__ == "__main__":
    main()
