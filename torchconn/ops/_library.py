"""The ``torchconn`` namespace of ``torch.library`` custom ops and the rules every op shares.

Every hot op of :mod:`torchconn.ops` is declared once with :func:`torch.library.custom_op` as
``torchconn::<name>`` (see :data:`NAMESPACE`), with

* a default implementation in torch operations (the *generic* kernel: every device, every dtype);
* a CPU kernel that runs the compiled C code when :func:`torchconn.ops.backend.can_use_compiled`
  allows it and the generic code otherwise (the one switch lives in :mod:`.backend`);
* a fake implementation (shapes only: ``meta`` tensors, ``torch.compile``, ``torch.export``);
* an autograd registration whose backward is itself made of differentiable pieces (another
  custom op with its own autograd registration, or torch operations), so double backward,
  ``create_graph=True`` and Hessian-vector products are exact on every path;
* a vmap rule (:func:`leading_vmap`) where the op takes native leading batch dimensions.
"""
from __future__ import annotations

from typing import Callable, Sequence

import torch

__all__ = ["NAMESPACE", "qualname", "leading_vmap", "scale_saved", "eager_function"]

#: The ``torch.library`` namespace of every torchconn op (``torch.ops.torchconn.<name>``).
NAMESPACE = "torchconn"


def qualname(name: str) -> str:
    """``"torchconn::<name>"``."""
    return f"{NAMESPACE}::{name}"


def leading_vmap(op: Callable, name: str, batched: Sequence[int], n_out: int = 1, summed: bool = False):
    """A vmap rule for an op whose arguments ``batched`` take native leading batch dimensions.

    The vmapped dimension of each of those arguments is moved to the front (an argument that is
    not vmapped is expanded to the batch size); the op then runs once on the whole batch and
    every output carries the batch at dimension 0. Any other argument (index tables, scalars)
    must not be vmapped: that raises ``ValueError`` naming the op and the argument.

    ``summed=True``: some output of the op is summed over the leading batch dimensions (the
    gradient of a mesh-level input such as the edge vectors); under vmap every item needs its
    own, so the op runs once per vmapped item (a loop over the vmap batch, not over mesh
    elements) and the outputs are stacked.
    """
    batched = tuple(batched)

    def rule(info, in_dims, *args):
        args = list(args)
        for i, d in enumerate(in_dims):
            if i in batched:
                if d is None:
                    args[i] = args[i].unsqueeze(0).expand(info.batch_size, *args[i].shape)
                elif d != 0:
                    args[i] = args[i].movedim(d, 0)
            elif d is not None:
                raise ValueError(
                    f"torchconn::{name}: vmap over argument {i} is not supported "
                    f"(only arguments {list(batched)} take leading batch dimensions)")
        if summed:
            items = [op(*[a[b] if i in batched else a for i, a in enumerate(args)]) for b in range(info.batch_size)]
            out = torch.stack(items) if n_out == 1 else tuple(torch.stack(o) for o in zip(*items))
        else:
            out = op(*args)
        return out, (0 if n_out == 1 else (0,) * n_out)

    return rule


def jvp(f: Callable, primals: Sequence[torch.Tensor], tangents: Sequence[torch.Tensor | None]):
    """Forward-mode derivative ``J t`` of the torch function ``f`` at ``primals`` (double-vjp identity).

    For use inside an ``autograd.Function.jvp``. Under a functorch transform it is
    ``torch.func.jvp``; under the ``torch.autograd.forward_ad`` API ``torch.func.jvp`` would open
    a nested forward-AD level, which is refused ("Nested forward mode AD is not supported"),
    so there it uses reverse mode: with ``g(u) = Jᵀ u`` (a reverse-mode product, linear in ``u``),
    ``J t = (∂g/∂u)ᵀ t``: two reverse passes through the generic formula, no dual level.
    ``tangents`` may hold ``None`` (no tangent for that input). Returns a tensor, or a tuple when
    ``f`` returns one.
    """
    if torch._C._functorch.get_interpreter_stack():
        # inside a functorch transform (torch.func.jvp, vmap, grad): its own jvp nests fine,
        # while reverse mode on fresh leaves (requires_grad_) is refused there
        tans = tuple(torch.zeros_like(p) if t is None else t for p, t in zip(primals, tangents))
        return torch.func.jvp(f, tuple(primals), tans)[1]
    with torch.enable_grad():
        xs = [p.detach().requires_grad_(p.is_floating_point()) for p in primals]
        out = f(*xs)
        outs = out if isinstance(out, tuple) else (out,)
        us = [torch.zeros_like(o).requires_grad_() for o in outs]
        diff = [(x, t) for x, t in zip(xs, tangents) if t is not None and x.requires_grad]
        res = [None] * len(outs)
        if diff:
            gs = torch.autograd.grad(outs, [x for x, _ in diff], us, create_graph=True, allow_unused=True)
            pairs = [(g, t) for g, (_, t) in zip(gs, diff) if g is not None and g.requires_grad]
            if pairs:
                res = list(torch.autograd.grad([g for g, _ in pairs], us, [t for _, t in pairs],
                                               allow_unused=True))
    res = tuple(torch.zeros_like(o) if r is None else r for r, o in zip(res, outs))
    return res if isinstance(out, tuple) else res[0]


def scale_saved(saved: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """A gradient computed in an op's forward (``saved (*B, ...)``) times the incoming gradient
    ``g (*B,)`` of the op's scalar output: the first-order backward of the fused sqnorm ops.

    When ``g`` is a plain CPU scalar equal to 1 (the backward of a loss, ``loss.backward()``) the
    saved tensor itself is returned: no pass over it and no fresh allocation (two of each per
    training step at 1M tets, ~17 ms each on a 2-core VM). Autograd never writes into a gradient
    it does not own (it accumulates in place only into a buffer nothing else references), so the
    saved tensor stays intact for a second backward. Under a ``torch.func`` transform, a
    ``torch.compile`` trace or on another device (where reading ``g`` would synchronize) it multiplies.
    """
    if (type(g) is torch.Tensor and g.device.type == "cpu" and g.numel() == 1 and not torch.compiler.is_compiling()
            and not torch._C._functorch.is_functorch_wrapped_tensor(g) and g.item() == 1.0):
        return saved
    return saved * g.reshape(*g.shape, *(1,) * (saved.dim() - g.dim()))


def eager_function(name: str, op: Callable, setup: Callable, backward: Callable, jvp: Callable,
                   n_forward: int, vmap: bool = True) -> type:
    """The ``torch.autograd.Function`` through which a fused op with gradient outputs runs eagerly
    and under the ``torch.func`` transforms (the autograd that ``register_autograd`` generates has
    no ``setup_context``, which ``torch.func.grad`` refuses, and no forward mode).

    ``forward`` calls ``op``; ``setup_context`` runs the op's ``setup(ctx, inputs, output)``, keeps
    the first ``n_forward`` inputs for forward mode and leaves unused gradients ``None`` (no zero
    tensors for the op's gradient outputs); ``backward`` is the op's ``backward(ctx, *grads)``;
    ``jvp(ctx, *tangents)`` gets the kept inputs as ``ctx.saved_tensors`` (forward mode only);
    ``vmap``: a generated vmap rule (it reaches the op's own vmap rule).
    """
    def setup_context(ctx, inputs, output):
        setup(ctx, inputs, output)
        ctx.save_for_forward(*inputs[:n_forward])
        ctx.set_materialize_grads(False)

    attrs = {"generate_vmap_rule": vmap,
             "forward": staticmethod(lambda *args: op(*args)),
             "setup_context": staticmethod(setup_context),
             "backward": staticmethod(backward),
             "jvp": staticmethod(jvp),
             "__doc__": f"``{name}`` for eager calls and the ``torch.func`` transforms (:func:`eager_function`)."}
    return type(name, (torch.autograd.Function,), attrs)
