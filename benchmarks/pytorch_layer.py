"""torchconn as a PyTorch layer: batched vs a loop, torch.compile vs eager, HVP vs first order.

    python -m benchmarks.pytorch_layer [--box 20] [--batch 8] [--repeats 5] [--dtype float32]
                                       [--device cpu] [--threads 2] [--no-compile]

The loss is the design card's: ``Σ‖Ω_f‖² + Σ‖τ_f‖² + Σ‖d∇d∇θ_t‖²`` of a connection given by skew
parameters ``ω (..., E, 3)`` (``R = so3.exp(ω)``) through the modules ``Curvature``, ``Torsion``
and ``AveragedCovariantD`` on one box mesh of ``6·box³`` tets. Every figure is the median over
``--repeats`` runs after a warm-up, all rows of one run side by side:

* **batched vs loop** — forward+backward of the loss on a batch ``ω (B, E, 3)`` in one call,
  against a Python loop over the ``B`` items (same values: checked);
* **compiled vs eager** — ``torch.compile(loss, fullgraph=True)`` (compile time printed
  separately) against the eager call, forward+backward, one item;
* **HVP vs first order** — ``torch.autograd.functional.hvp`` (double backward through every
  op) against ``torch.autograd.grad`` of the same loss, one item.

On CUDA the timer synchronizes the device.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from torchconn import io, so3
from torchconn.nn import AveragedCovariantD, Curvature, Torsion


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(fn, repeats: int, device: torch.device) -> float:
    fn()
    _sync(device)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def make_loss(mesh):
    """``ω (..., E, 3) -> scalar``: the curvature + torsion + averaged-d∇ loss (summed over the batch)."""
    curv, tors, dd = Curvature(mesh), Torsion(mesh), AveragedCovariantD(mesh)

    def loss(omega: torch.Tensor) -> torch.Tensor:
        R = so3.exp(omega)
        return curv(R).square().sum() + tors(R).square().sum() + dd(R).square().sum()

    return loss


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--box", type=int, default=20)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-compile", action="store_true", help="skip the torch.compile row")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    dtype, device = getattr(torch, args.dtype), torch.device(args.device)
    mesh = io.box(n=args.box).to(device=device, dtype=dtype)
    E = int(mesh.edges.shape[0])
    loss = make_loss(mesh)
    gen = torch.Generator().manual_seed(0)
    omega_b = (0.3 * torch.randn(args.batch, E, 3, generator=gen, dtype=dtype)).to(device).requires_grad_()
    omega = omega_b[0].detach().clone().requires_grad_()
    print(f"box(n={args.box}): {int(mesh.tets.shape[0]):,} tets, {E:,} edges; {args.dtype} on {device}; "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads")

    # ------------------------------------------------------------------ batched vs loop
    def batched():
        omega_b.grad = None
        loss(omega_b).backward()

    def looped():
        omega_b.grad = None
        sum(loss(omega_b[b]) for b in range(args.batch)).backward()

    with torch.no_grad():
        vb, vl = loss(omega_b), sum(loss(omega_b[b]) for b in range(args.batch))
    rel = float((vb - vl).abs() / vl.abs().clamp_min(1e-30))
    rows = [("batched B=%d, fwd+bwd" % args.batch, _time(batched, args.repeats, device)),
            ("loop over %d, fwd+bwd" % args.batch, _time(looped, args.repeats, device))]

    # ------------------------------------------------------------------ compiled vs eager
    def eager():
        omega.grad = None
        loss(omega).backward()

    rows.append(("eager, fwd+bwd", _time(eager, args.repeats, device)))
    if not args.no_compile:
        closs = torch.compile(loss, fullgraph=True)
        t0 = time.perf_counter()
        closs(omega).backward()
        _sync(device)
        t_compile = time.perf_counter() - t0

        def compiled():
            omega.grad = None
            closs(omega).backward()

        rows.append(("torch.compile(fullgraph=True), fwd+bwd", _time(compiled, args.repeats, device)))
        with torch.no_grad():
            crel = float((closs(omega) - loss(omega)).abs() / loss(omega).abs())
    # ------------------------------------------------------------------ HVP vs first order
    v = torch.randn(omega.shape, generator=gen, dtype=dtype).to(device)
    w = omega.detach()

    def first_order():
        x = w.clone().requires_grad_()
        torch.autograd.grad(loss(x), x)

    def hvp():
        torch.autograd.functional.hvp(loss, w, v)

    rows.append(("first order: autograd.grad", _time(first_order, args.repeats, device)))
    rows.append(("second order: autograd.functional.hvp", _time(hvp, args.repeats, device)))

    print(f"batched vs loop: loss values agree to {rel:.1e} (relative)")
    if not args.no_compile:
        print(f"torch.compile: first call (compile + run) {t_compile:.1f} s; value agrees to {crel:.1e}")
    print("| row | time (ms) |")
    print("|---|---|")
    for name, t in rows:
        print(f"| {name} | {t * 1e3:.1f} |")
    d = dict(rows)
    b, l = rows[0][1], rows[1][1]
    print(f"ratios: loop/batched {l / b:.2f}; "
          + (f"eager/compiled {d['eager, fwd+bwd'] / d['torch.compile(fullgraph=True), fwd+bwd']:.2f}; "
             if not args.no_compile else "")
          + f"hvp/first order {d['second order: autograd.functional.hvp'] / d['first order: autograd.grad']:.2f}")


if __name__ == "__main__":
    main()
