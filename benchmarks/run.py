"""Benchmark suite of issue 6: fused kernels against eager references, side by side.

    python -m benchmarks.run [--quick] [--output-dir DIR] [--threads N] [--repeats R] [--only CASE ...]
                             [--sizes TETS ...] [--dtypes float32 float64]

Prints a markdown table and writes ``DIR/benchmark.json``: a list of
``{name, size, dtype, seconds, reference_seconds, ratio, peak_mb, ...}`` (``ratio`` =
reference / fast; extra keys: ``reference``, ``max_abs_diff``, ``unit``, ``note``).

Cases
-----
1. ``so3.exp`` / ``so3.log`` / ``so3.sqrt`` forward+backward on 10⁶ rotations (10⁵ with
   ``--quick``), float32, as the library routes them (the compiled ``csrc/so3.c`` kernels when
   :mod:`torchconn.ops.native` builds them, recorded as ``path``) against
   ``torch.linalg.matrix_exp(hat(ω))`` (exp), the previous matrix-based ``so3.log`` kept in :mod:`benchmarks.references`
   (``_ref_log``; there is no matrix-log route in torch), ``exp(log(R)/2)`` through those
   references (sqrt), the same op with the compiled kernels switched off
   (``torchconn.ops.compiled(False)``: the torch code of :mod:`torchconn.ops.so3`, the fallback;
   ``*_vs_torch`` rows) and ``roma`` when it is installed (``*_vs_roma`` rows).
   ``max_abs_diff`` is the largest entry difference of the forward values (log against the
   matrix log and roma: through ``exp``, both signs being logarithms at angle π).
   ``so3.log_validation(fwd)`` / ``(fwd+bwd)``: ``torchconn.so3.log`` (validated; its compiled
   kernel counts the non-rotations in the same pass) against the unvalidated
   ``torchconn.ops.so3.log``, the overhead in the note. ``path`` records ``-march`` (set
   ``TORCHCONN_MARCH=x86-64-v3`` to time the AVX2 code on an AVX-512 machine).
2. Curvature + averaged ``d∇d∇θ̃`` (and torsion alone) on box meshes of ~10k, 100k, 1M tets
   (``io.box(n)``, ``6 n³`` tets; ``--quick`` stops at 100k), float32 and float64, from a
   ``ConnectionField``-like parameter tensor (``so3.exp`` of skew params), loss
   ``Σ‖Ω_f‖² + Σ‖d∇d∇θ̃_t‖²``, backward to the params. Reference: the generic path (dense
   per-tet tables ``dnabla.tet_transports`` / ``tet_solder_sqrt`` / ``averaged_dd_tet``, loop
   curvature ``orient`` + ``curvature.two_prong``, matrix-route ``exp`` / ``sqrt``).
   ``curvature+averaged_dnabla(sqnorm)``: the same loss through the modules' fused
   ``Curvature.sqnorm`` + ``AveragedCovariantD.sqnorm`` (value and gradient in one sweep each, no
   ``(F, 3, 3)`` / ``(T, 3)`` tensors: the form a loss runs; issue 30's target row).
3. The frame-field loss (:class:`torchconn.frames.loss.FrameFieldLoss`) at the same sizes, forward +
   backward to connection params and per-vertex frame params: ``frame_field_loss(default)``, the
   loss ``design()`` runs by default (:func:`loss_cases`: its weights and options; torsion through
   the matchings on every face, the averaged d∇ on the regular tets), and
   ``frame_field_loss(all terms)``, every term weighted 1. Each against an eager composition of
   the library's single-term functions (:func:`benchmarks.references.ref_frame_loss_terms`: generic curvature
   and torsion loops, dense d∇ tables, ``matrix_exp``), which must agree with the loss to
   ``LOSS_AGREEMENT_RTOL`` relative on every term and the total (:func:`loss_agreement`, measured
   in the row's dtype; ``tests/test_losses.py`` asserts it on a small mesh): a row whose reference
   disagrees is reported as failed (``failed``, no time). ``frame_field_loss(default)_vs_modules``:
   the same loss with the compiled kernels off (its term modules, each through its own ops).
4. End to end (not with ``--quick``): ``python -m training.train_frames`` on
   ``../shared/data/78322_gear.2.mesh`` (one subprocess run, wall time) and mouette's Ray et al.
   2016 ``VolumeFrameField(mesh, "vertices")`` on the same mesh when ``mouette`` is installed (in a
   subprocess, ``--mouette-timeout`` seconds; a run that does not finish is reported as such).
   ``benchmark.json`` is rewritten after every case, so partial results survive an interrupt.
5. Under load (only with ``--only under_load``): :mod:`benchmarks.under_load`'s training step
   with one thread and with torch's default threads, unloaded and while a spinner process holds
   a core, once per OpenMP wait policy (default, PASSIVE) in a child process; ``ratio`` =
   one-thread time / default-threads time (issue 24's target with the spinner: >= 1/1.5).

Timing: each figure is the median of ``--repeats`` runs after one warm-up run; fast and
reference are measured in the same process, one after the other (``ratio`` is taken side by
side): the fast runs first, as a block, then the reference's — at 1M tets the eager reference
allocates tens of GB, and the fast runs right after it were measured 0.60–0.85 s against
0.46 s before it (the all-terms loss, 2026-11-27: a cold effect that lasts several runs, which
alternating the two put into the fast figure; an optimization loop runs the fast path back to
back). The
operator and loss rows also record ``cpu_seconds``, the median process CPU time (all threads) of
the fast runs: on a machine other processes load, wall time measures the load too, CPU time much
less (the table prints it in the note). At
≥ 1M tets the reference is run once after its warm-up (it takes tens of seconds; noted in the
row). ``--threads`` sets ``torch.set_num_threads`` (default: torch's default). On a shared
machine torch's own OpenMP threads spin at their barriers (unless ``OMP_WAIT_POLICY=PASSIVE``
was set before Python started), which can make a loaded 2-core box ~10× slower per op than
one thread; record the thread count and the load with the figures. ``--malloc resident`` (default) keeps freed memory in
the process (:func:`keep_memory_resident`); without it, page faults of re-mmapped large
temporaries make the time per tet at 1M ~1.8x that at 100k. Both are recorded in the JSON.

Peak memory (``peak_mb``): a sampler thread reads the resident set size (``/proc/self/statm``)
every millisecond during one extra fast run; the figure is the peak minus the RSS just before
the run. For that run glibc is told to mmap every block of 64 KB or more (``mallopt``), so
that freed tensors leave the RSS and it follows the live tensors (see :func:`_peak_mb`). It is
the extra memory of the fast path, inputs and parameters excluded (autograd graph, outputs and
gradients included). ``resource.getrusage``'s ``ru_maxrss`` is a process-lifetime high-water
mark and cannot isolate one case.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from torchconn import curvature, dnabla, io, so3
import torchconn.ops
from torchconn.ops import so3 as ops_so3
from torchconn import torsion as _torsion
from torchconn.nn import AveragedCovariantD, Curvature

from .references import (LOSS_AGREEMENT_RTOL, _ref_dd, _ref_exp_matrix, _ref_face_curvature,
                         _ref_face_torsion, _ref_log, _ref_sqrt, loss_agreement, loss_cases, ref_frame_loss_terms)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
GEAR = DATA / "78322_gear.2.mesh"


# ----------------------------------------------------------------------------- measurement

class _RSSPeak:
    """Peak resident set size (bytes) above the value at entry, sampled every ``dt`` seconds."""

    def __init__(self, dt: float = 1e-3):
        self.dt, self.peak, self._stop = dt, 0, threading.Event()
        self._page = os.sysconf("SC_PAGE_SIZE")

    def _rss(self) -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * self._page

    def _loop(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss() - self.base)
            time.sleep(self.dt)

    def __enter__(self):
        self.base = self._rss()
        self._t = threading.Thread(target=self._loop, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self._rss() - self.base)


def _libc():
    try:
        import ctypes

        lib = ctypes.CDLL("libc.so.6")
        lib.mallopt, lib.malloc_trim  # noqa: B018 (glibc only)
        return lib
    except (OSError, AttributeError):
        return None


_M_MMAP_THRESHOLD = -3
_M_TRIM_THRESHOLD = -1


_RESIDENT = {"on": False}


def keep_memory_resident() -> bool:
    """Ask glibc to keep freed memory in the process (``mallopt``): no mmap below 1 GB, no trim.

    By default glibc serves blocks above its dynamic mmap threshold (at most 32 MB) with fresh
    ``mmap`` calls and unmaps them on free, so every large temporary of an eager step costs page
    faults and kernel zeroing again; at 1M tets that is ~40% of the step. Equivalent to the
    environment variables ``MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=2147483647``.
    Returns False where glibc is not available.
    """
    lib = _libc()
    if lib is None:
        return False
    ok = lib.mallopt(_M_MMAP_THRESHOLD, 2**30) == 1 and lib.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1
    _RESIDENT["on"] = ok
    return ok


def _peak_mb(fn) -> float:
    """Extra resident memory of one ``fn()`` call (MB); NaN where it cannot be measured.

    glibc keeps freed heap blocks resident and raises its mmap threshold dynamically (up to
    32 MB), so after a warm-up the RSS would not grow at all. For this one run every block of
    64 KB or more is mmapped (``mallopt(M_MMAP_THRESHOLD, 64 KB)``, after ``malloc_trim``), so
    RSS follows the live tensors; the threshold is set back afterwards (1 GB with
    :func:`keep_memory_resident`, else 32 MB, the top of glibc's dynamic range, where it sits
    after the warm-ups) for the following timings.
    """
    lib = _libc()
    if lib is None or not Path("/proc/self/statm").exists():
        return float("nan")
    lib.mallopt(_M_MMAP_THRESHOLD, 64 * 1024)
    lib.malloc_trim(0)
    try:
        with _RSSPeak() as p:
            fn()
        return p.peak / 2**20
    finally:
        lib.mallopt(_M_MMAP_THRESHOLD, 2**30 if _RESIDENT["on"] else 32 * 2**20)


#: Process CPU seconds of the fast runs of the last :func:`_side_by_side` (median): on a machine
#: other processes load, wall time measures the load as much as the code; the CPU time of the
#: process (all its threads) much less so. Recorded as ``cpu_seconds`` where the rows take it.
_LAST_CPU = {"fast": None}


def _side_by_side(fast_fn, ref_fn, repeats: int, ref_repeats: int | None = None):
    """Medians of the fast runs, then of the reference's, each after one warm-up: ``(fast_s, ref_s)``
    (wall time; module doc: the fast block first, so the reference's memory churn is not in it);
    the median process CPU time of the fast runs goes to ``_LAST_CPU["fast"]``."""
    ref_repeats = repeats if ref_repeats is None else ref_repeats
    tf, tr, cf = [], [], []
    fast_fn()
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fast_fn()
        tf.append(time.perf_counter() - t0)
        cf.append(time.process_time() - c0)
    if ref_fn is not None:
        ref_fn()
        for _ in range(ref_repeats):
            t0 = time.perf_counter()
            ref_fn()
            tr.append(time.perf_counter() - t0)
    _LAST_CPU["fast"] = statistics.median(cf)
    return statistics.median(tf), (statistics.median(tr) if tr else None)


def _row(name, size, dtype, seconds, ref_seconds, peak_mb, **extra):
    ratio = (ref_seconds / seconds) if (ref_seconds is not None and seconds) else None
    row = {"name": name, "size": size, "dtype": dtype, "seconds": seconds,
           "reference_seconds": ref_seconds, "ratio": ratio, "peak_mb": peak_mb,
           "loadavg_1min": os.getloadavg()[0]}  # the machine's load when the row was written
    row.update(extra)
    return row


# ----------------------------------------------------------------------------- cases

def bench_so3(n: int, repeats: int, rows: list) -> None:
    g = torch.Generator().manual_seed(0)
    w = (torch.randn(n, 3, generator=g) * 1.0).requires_grad_()
    R = so3.exp(w.detach()).requires_grad_()
    try:
        import roma
    except ImportError:
        roma = None
    # which path so3.exp/log/sqrt take here (compiled csrc/so3.c, for which -march, or the torch code)
    march = os.environ.get("TORCHCONN_MARCH", "").strip() or "native"
    path = (f"compiled C (-march={march})" if torchconn.ops.can_use_compiled("so3", w)
            else "torch (compiled kernels unavailable)")

    def fb(f, x):
        def run():
            x.grad = None
            f(x).sum().backward()
        return run

    class torch_path:
        """``f`` with the compiled kernels switched off in the forward *and* the backward (the
        backward op picks its kernel when autograd runs it: a switch around the forward call
        alone left the reference's backward compiled, until 2026-11-25)."""

        def __init__(self, f):
            self.f = f

        def __call__(self, x):
            with torchconn.ops.compiled(False):
                return self.f(x)

    def fb_ref(ref, x):
        run = fb(ref, x)
        if not isinstance(ref, torch_path):
            return run

        def run_off():
            with torchconn.ops.compiled(False):
                run()
        return run_off

    cases = [
        ("so3.exp", so3.exp, w, _ref_exp_matrix, "matrix_exp(hat(w))"),
        ("so3.exp_vs_torch", so3.exp, w, torch_path(so3.exp), "torch closed form (compiled kernels off)"),
        ("so3.log", so3.log, R, _ref_log, "previous matrix-based so3.log"),
        ("so3.log_vs_torch", so3.log, R, torch_path(so3.log), "torch branches (compiled kernels off)"),
        ("so3.sqrt", so3.sqrt, R, _ref_sqrt, "exp(log(R)/2), previous so3 exp/log"),
        ("so3.sqrt_vs_torch", so3.sqrt, R, torch_path(so3.sqrt), "torch half-angle (compiled kernels off)"),
    ]
    if roma is not None:
        cases += [("so3.exp_vs_roma", so3.exp, w, roma.rotvec_to_rotmat, f"roma {roma.__version__} rotvec_to_rotmat"),
                  ("so3.log_vs_roma", so3.log, R, roma.rotmat_to_rotvec, f"roma {roma.__version__} rotmat_to_rotvec")]
    for name, f, x, ref, ref_name in cases:
        t, tr = _side_by_side(fb(f, x), fb_ref(ref, x), repeats)
        with torch.no_grad():
            a, b = f(x), ref(x)
            if name in ("so3.log", "so3.log_vs_roma"):  # angle-pi sign ambiguity: compare through exp
                diff = float((so3.exp(a) - so3.exp(b)).abs().max())
            else:
                diff = float((a - b).abs().max())
        rows.append(_row(name, n, "float32", t, tr, _peak_mb(fb(f, x)), reference=ref_name,
                         max_abs_diff=diff, unit="rotations", path=path))
    if roma is None:
        rows.append(_row("so3.exp_vs_roma", n, "float32", None, None, None, note="roma not installed"))
    # the cost of validation: torchconn.so3.log (checked: the compiled kernel counts the matrices
    # that are not rotations in the same pass) against the unvalidated torchconn.ops.so3.log
    def fwd(f, x):
        def run():
            with torch.no_grad():
                f(x)
        return run

    for label, make in (("fwd", fwd), ("fwd+bwd", fb)):
        t, tr = _side_by_side(make(so3.log, R), make(ops_so3.log, R), repeats)
        rows.append(_row(f"so3.log_validation({label})", n, "float32", t, tr, None, unit="rotations", path=path,
                         reference="torchconn.ops.so3.log (unvalidated)",
                         note=f"validation adds {100 * (t / tr - 1):+.0f}% (target <= +20%)"))


def _box(tets: int, dtype):
    n = max(1, round((tets / 6) ** (1 / 3)))
    return io.box(n).to(dtype=dtype)


def bench_operators(tets: int, dtype, repeats: int, rows: list) -> None:
    mesh = _box(tets, dtype)
    T = int(mesh.tets.shape[0])
    g = torch.Generator().manual_seed(1)
    w = (0.3 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=dtype)).requires_grad_()
    dname = str(dtype).replace("torch.", "")
    big = T >= 500_000
    ref_rep = 1 if big else repeats

    def fast_cd():
        w.grad = None
        R = so3.exp(w)
        (curvature.face_curvature(R, mesh).square().sum()
         + dnabla.averaged_dd_solder(R, mesh, half_rot=ops_so3.half_exp(w)).square().sum()).backward()

    def fast_cd_sqrt():
        w.grad = None
        R = so3.exp(w)
        (curvature.face_curvature(R, mesh).square().sum()
         + dnabla.averaged_dd_solder(R, mesh).square().sum()).backward()

    curv_mod, dd_mod = Curvature(mesh), AveragedCovariantD(mesh)

    def fast_cd_sqnorm():
        w.grad = None
        R = so3.exp(w)
        (curv_mod.sqnorm(R) + dd_mod.sqnorm(R)).backward()

    def ref_cd():
        w.grad = None
        R = _ref_exp_matrix(w)
        (_ref_face_curvature(R, mesh).square().sum() + _ref_dd(R, mesh).square().sum()).backward()

    def fast_tor():
        w.grad = None
        _torsion.face_torsion(so3.exp(w), mesh).square().sum().backward()

    def ref_tor():
        w.grad = None
        _ref_face_torsion(_ref_exp_matrix(w), mesh).square().sum().backward()

    with torch.no_grad():
        R = so3.exp(w)
        d_cd = max(float((curvature.face_curvature(R, mesh) - _ref_face_curvature(R, mesh)).abs().max()),
                   float((dnabla.averaged_dd_solder(R, mesh) - _ref_dd(R, mesh)).abs().max()))
        d_tor = float((_torsion.face_torsion(R, mesh) - _ref_face_torsion(R, mesh)).abs().max())
        ref_sum = _ref_face_curvature(R, mesh).square().sum() + _ref_dd(R, mesh).square().sum()
        d_sqn = float(((curv_mod.sqnorm(R) + dd_mod.sqnorm(R)) - ref_sum).abs() / ref_sum.abs())
    ref_name = "generic dense dnabla + loop curvature, matrix_exp"
    note = "reference: 1 run after warm-up" if big else ""
    t, tr = _side_by_side(fast_cd, ref_cd, repeats, ref_rep)
    rows.append(_row("curvature+averaged_dnabla", T, dname, t, tr, _peak_mb(fast_cd), reference=ref_name,
                     cpu_seconds=_LAST_CPU["fast"],
                     max_abs_diff=d_cd, unit="tets", note=("√R = exp(ω/2) from params; " + note).strip("; ")))
    t2, _ = _side_by_side(fast_cd_sqrt, None, repeats)
    rows.append(_row("curvature+averaged_dnabla(sqrt)", T, dname, t2, tr, _peak_mb(fast_cd_sqrt),
                     cpu_seconds=_LAST_CPU["fast"],
                     reference=ref_name, unit="tets", note=("√R = so3.sqrt(R); " + note).strip("; ")))
    t4, _ = _side_by_side(fast_cd_sqnorm, None, repeats)
    rows.append(_row("curvature+averaged_dnabla(sqnorm)", T, dname, t4, tr, _peak_mb(fast_cd_sqnorm),
                     cpu_seconds=_LAST_CPU["fast"], reference=ref_name, unit="tets",
                     note=(f"Curvature.sqnorm + AveragedCovariantD.sqnorm (the loss's fused form; value "
                           f"{d_sqn:.1e} relative to the reference's sum); " + note).strip("; ")))
    t3, tr3 = _side_by_side(fast_tor, ref_tor, repeats, ref_rep)
    rows.append(_row("torsion(sqrt)", T, dname, t3, tr3, _peak_mb(fast_tor), reference="generic loop torsion",
                     cpu_seconds=_LAST_CPU["fast"],
                     max_abs_diff=d_tor, unit="tets", note=note))


def bench_loss(tets: int, dtype, repeats: int, rows: list) -> None:
    """The loss rows (module doc, case 3): design()'s default loss and the all-terms variant against
    the eager reference, and the default loss against its own modules (the fused kernel off)."""
    dname = str(dtype).replace("torch.", "")
    mesh = _box(tets, dtype)
    T = int(mesh.tets.shape[0])
    g = torch.Generator().manual_seed(2)
    w = (0.2 * torch.randn(mesh.edges.shape[0], 3, generator=g, dtype=dtype)).requires_grad_()
    phi = (0.2 * torch.randn(mesh.vertices.shape[0], 3, generator=g, dtype=dtype)).requires_grad_()
    big = T >= 500_000
    cases = loss_cases(mesh)  # imports torchconn.frames.kernels, which registers the kernel's C source
    path = ("compiled kernels frames/kernels/csrc/frame_loss.c + ops/csrc/tet.c (dnabla: tet_dd_frames_sqnorm)"
            if torchconn.ops.can_use_compiled("frame_loss", w, phi) else "modules (no compiled kernel)")
    for name, loss in cases:
        def fast_fn(loss=loss):
            w.grad = phi.grad = None
            loss(so3.exp(w), so3.exp(phi))["total"].backward()

        def ref_fn(loss=loss):
            w.grad = phi.grad = None
            ref_frame_loss_terms(loss, _ref_exp_matrix(w), _ref_exp_matrix(phi))["total"].backward()

        rel, worst = loss_agreement(loss, so3.exp(w.detach()), so3.exp(phi.detach()))
        weights = ", ".join(f"{k} {v:g}" for k, v in loss.weights.items() if v)
        note = (f"{weights}; smooth_power {loss.smooth_power:g}, align {loss.align_kind}; fwd+bwd to edge and "
                f"vertex params; {path}" + ("; reference: 1 run after warm-up" if big else ""))
        if rel > LOSS_AGREEMENT_RTOL:
            rows.append(_row(name, T, dname, None, None, None, unit="tets", max_rel_diff=rel,
                             failed=f"reference disagrees: {worst} differs by {rel:.2g} relative "
                                    f"(> {LOSS_AGREEMENT_RTOL:g})", note=note))
            continue
        t, tr = _side_by_side(fast_fn, ref_fn, repeats, 1 if big else repeats)
        rows.append(_row(name, T, dname, t, tr, _peak_mb(fast_fn), unit="tets", max_rel_diff=rel,
                         cpu_seconds=_LAST_CPU["fast"],
                         reference="eager composition of the library's single-term functions (generic "
                                   "curvature/torsion loops, dense d∇ tables, matrix_exp)", note=note))
        if name.endswith("(default)"):
            # the same loss with the compiled kernels off: its term modules through their own ops' kernels
            def modules_fn(loss=loss):
                w.grad = phi.grad = None
                with torchconn.ops.compiled(False):
                    loss(so3.exp(w), so3.exp(phi))["total"].backward()

            with torch.no_grad(), torchconn.ops.compiled(False):
                rel_m, _ = loss_agreement(loss, so3.exp(w), so3.exp(phi))
            t2, tr2 = _side_by_side(fast_fn, modules_fn, repeats)
            rows.append(_row(name + "_vs_modules", T, dname, t2, tr2, None, unit="tets", max_rel_diff=rel_m,
                             reference="the same FrameFieldLoss with torchconn.ops.compiled(False): its term modules",
                             note="fused kernel vs the loss's modules, side by side"))


_E2E_KEYS = ("smoothness_mean_deg", "alignment_mean_deg", "feature_alignment_mean_deg", "n_singular_faces")


def bench_end_to_end(rows: list, threads: int, mouette_timeout: float = 600.0) -> None:
    """The main job on the gear (wall time incl. startup) and mouette's Ray 2016 field, with metrics.

    mouette runs through :func:`benchmarks.compare_frames._run_mouette` (subprocess with a time
    limit, boundary-first vertex renumbering, frames evaluated with our metrics). The ratio is
    mouette's wall time over ours; both metric sets go into the row (``ours``, ``mouette``).
    """
    if not GEAR.exists():
        rows.append(_row("train_frames(gear)", None, "float64", None, None, None, note=f"not measured: {GEAR} missing"))
        return
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "training.train_frames", f"mesh={GEAR}", f"output_dir={tmp}",
               f"num_threads={threads}", "progress=false"]
        t0 = time.perf_counter()
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        dt = time.perf_counter() - t0
        ours = {}
        if res.returncode == 0:
            final = json.loads((Path(tmp) / "metrics.json").read_text())["final"]
            ours = {k: final.get(k) for k in _E2E_KEYS}
    if res.returncode != 0:
        rows.append(_row("train_frames(gear)", GEAR.name, "float64", None, None, None,
                         note=f"failed (rc {res.returncode}): {res.stderr.strip().splitlines()[-1:]}"))
        return
    try:
        import mouette as M
        from benchmarks.compare_frames import _run_mouette
    except ImportError as exc:
        rows.append(_row("train_frames(gear)", GEAR.name, "float64", dt, None, None, ours=ours,
                         note=f"one run, wall incl. startup, SH init, metrics, plots; mouette not run: {exc}"))
        return
    ver = getattr(M, "__version__", "?")
    m = _run_mouette(GEAR, None, mouette_timeout, threads)
    ref = m.get("wall_s")
    theirs = {k: m["metrics"].get(k) for k in _E2E_KEYS} if "metrics" in m else {}
    note = (f"one run each, wall incl. startup; reference: mouette {ver} VolumeFrameField(mesh, 'vertices').run()"
            + (f" ({m['error']})" if "error" in m else ""))
    def brief(d):
        return ", ".join(f"{k.replace('_deg', '')}={v:.3g}" for k, v in d.items() if v is not None) or "n/a"

    note += f"; ours: {brief(ours)}; mouette: {brief(theirs)}"
    rows.append(_row("train_frames(gear) vs mouette", GEAR.name, "float64", dt, ref, None, ours=ours,
                     mouette=theirs, note=note, command=" ".join(cmd[1:])))


def bench_under_load(rows: list, steps: int) -> None:
    """:mod:`benchmarks.under_load`: a training step (MLP -> so3.exp -> Curvature +
    AveragedCovariantD, Adam) with one thread and with torch's default threads, side by side,
    unloaded and while a spinner process holds the last CPU; each OpenMP wait policy in a fresh
    child process (default, PASSIVE). ``seconds`` = the default threads, ``reference_seconds`` =
    one thread per step, so ``ratio`` < 1 is the slowdown (target with the spinner: >= 1/1.5)."""
    from benchmarks import under_load

    for r in under_load.bench_policies(tuple(under_load.POLICIES), steps=steps, rounds=4):
        rows.append(_row(f"{r['name']} OMP_WAIT_POLICY={r['wait_policy']}", r["tets"], "float32",
                         r["ms_threads"] / 1e3, r["ms_1_thread"] / 1e3, None, unit="tets",
                         reference="the same step with 1 thread",
                         note=f"{r['threads']} threads / 1 thread = {r['ratio']:.2f}x; loadavg {r['loadavg']}"))


# ----------------------------------------------------------------------------- report

def _fmt(x, spec):
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def table(rows: list) -> str:
    lines = ["| case | size | dtype | fast (s) | reference (s) | ratio | peak (MB) | max diff | note |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        size = r["size"] if not isinstance(r["size"], int) else f"{r['size']:,} {r.get('unit', '')}".strip()
        diff = (f"{_fmt(r.get('max_rel_diff'), '.1e')} rel" if r.get("max_rel_diff") is not None
                else _fmt(r.get("max_abs_diff"), ".1e"))
        note = r.get("note", "") or r.get("reference", "")
        if r.get("cpu_seconds") is not None:
            note = f"CPU {r['cpu_seconds']:.3f} s; {note}"
        if r.get("failed"):
            note = f"**FAILED**: {r['failed']}; {note}"
        lines.append(f"| {r['name']} | {size} | {r['dtype']} | {_fmt(r['seconds'], '.4f')} | "
                     f"{_fmt(r['reference_seconds'], '.4f')} | {_fmt(r['ratio'], '.1f')}"
                     f"{'×' if r['ratio'] else ''} | {_fmt(r['peak_mb'], '.0f')} | {diff} | {note} |")
    return "\n".join(lines)


def main(argv=None) -> list:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="sizes <= 100k tets, 10^5 rotations, whole run < 2 min")
    ap.add_argument("--output-dir", type=Path, default=Path("."))
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per figure (default 5, quick 3)")
    ap.add_argument("--malloc", choices=["resident", "default"], default="resident",
                    help="resident: keep freed memory in the process (glibc mallopt, see keep_memory_resident); "
                         "default: glibc's defaults")
    ap.add_argument("--mouette-timeout", type=float, default=600.0, help="seconds for the mouette run")
    ap.add_argument("--only", nargs="+", default=None,
                    choices=["so3", "operators", "loss", "end_to_end", "under_load"])
    ap.add_argument("--sizes", nargs="+", type=int, default=None,
                    help="tet counts of the operator and loss rows (default 10k 100k 1M; quick: 10k 100k)")
    ap.add_argument("--dtypes", nargs="+", choices=["float32", "float64"], default=["float32", "float64"],
                    help="dtypes of the operator and loss rows")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()
    malloc = "resident" if args.malloc == "resident" and keep_memory_resident() else "default"
    repeats = args.repeats or (3 if args.quick else 5)
    sizes = args.sizes or ([10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000])
    only = set(args.only or ["so3", "operators", "loss"] + ([] if args.quick else ["end_to_end"]))
    print(f"torch {torch.__version__}, {threads} threads, repeats {repeats}, quick={args.quick}, "
          f"malloc={malloc}, load average {os.getloadavg()[0]:.1f} ({os.cpu_count()} CPUs)", flush=True)
    rows: list = []
    t_start = time.perf_counter()
    if "so3" in only:
        bench_so3(10**5 if args.quick else 10**6, repeats, rows)
        _save(rows, threads, malloc, args.output_dir)
    for dtype in (getattr(torch, d) for d in args.dtypes):
        for n in sizes:
            if "operators" in only:
                bench_operators(n, dtype, repeats, rows)
            if "loss" in only:
                bench_loss(n, dtype, repeats, rows)
            _save(rows, threads, malloc, args.output_dir)  # partial results survive an interruption
            print(f"  done {n} tets {dtype} ({time.perf_counter() - t_start:.0f} s)", flush=True)
    if "end_to_end" in only:
        bench_end_to_end(rows, threads, args.mouette_timeout)
        _save(rows, threads, malloc, args.output_dir)
    if "under_load" in only:
        bench_under_load(rows, 100 if args.quick else 400)
        _save(rows, threads, malloc, args.output_dir)
    _save(rows, threads, malloc, args.output_dir)
    print(table(rows))
    print(f"total {time.perf_counter() - t_start:.1f} s")
    return rows


def _save(rows: list, threads: int, malloc: str, out_dir: Path) -> None:
    for r in rows:
        r["threads"] = threads
        r["malloc"] = malloc
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "benchmark.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
