"""The frame-field solver: learning-rate schedule, optimizer and the optimization loop.

:func:`optimize` runs a model ``() -> (edge_rot (E, 3, 3), frames (V, 3, 3))``
(:class:`~torchconn.frames.model.FrameFieldModel`) against a loss ``(edge_rot, frames) -> {term:
0-dim tensor, ..., "total"}`` (:class:`~torchconn.frames.loss.FrameFieldLoss`) for a number of
optimizer steps, recording the unweighted terms; the caller checkpoints from the ``on_step``
callback. The state that makes a resumed run equal an uninterrupted one is the model's and
optimizer's and scheduler's ``state_dict``, the RNG state, the step and the history.
"""
from __future__ import annotations

import math
from typing import Callable, Mapping

import torch

from .loss import TERMS

__all__ = ["NonFiniteLossError", "cosine_factor", "make_optimizer", "new_history", "optimize",
           "check_finite_terms", "OPTIMIZERS", "LR_SCHEDULES"]

#: Optimizers of :func:`make_optimizer`.
OPTIMIZERS = ("adam", "lbfgs")
#: Learning-rate schedules of :func:`make_optimizer`.
LR_SCHEDULES = ("cosine", "constant")


class NonFiniteLossError(FloatingPointError):
    """A loss term became NaN/inf; the message names the term and the step."""


def cosine_factor(step: int, steps: int) -> float:
    """Cosine learning-rate factor ``(1 + cos(pi min(step, steps) / steps)) / 2``: 1 at step 0, 0 at ``steps``.

    The learning rate goes to 0 at the last step, so Adam settles instead of jittering around the
    minimum. ``steps < 1`` counts as 1; steps past ``steps`` stay at 0.
    """
    steps = max(int(steps), 1)
    return 0.5 * (1.0 + math.cos(math.pi * min(step, steps) / steps))


def make_optimizer(params, optim: str = "adam", lr: float = 0.02, steps: int = 1, schedule: str = "cosine",
                   lbfgs_history_size: int = 20, lbfgs_max_iter: int = 5):
    """``(optimizer, LambdaLR scheduler)`` for ``params``.

    ``optim``: ``"adam"`` or ``"lbfgs"`` (strong-Wolfe line search; one step runs up to
    ``lbfgs_max_iter`` iterations). ``schedule``: ``"cosine"`` (:func:`cosine_factor` over
    ``steps``) or ``"constant"``.
    """
    if optim not in OPTIMIZERS or schedule not in LR_SCHEDULES:
        raise ValueError(f"optim must be one of {list(OPTIMIZERS)} and schedule one of {list(LR_SCHEDULES)}, "
                         f"got {optim!r}, {schedule!r}")
    if optim == "adam":
        opt = torch.optim.Adam(params, lr=float(lr))
    else:
        opt = torch.optim.LBFGS(params, lr=float(lr), history_size=int(lbfgs_history_size),
                                max_iter=int(lbfgs_max_iter), line_search_fn="strong_wolfe")
    steps = max(int(steps), 1)
    if schedule == "cosine":
        fn = lambda s: cosine_factor(s, steps)  # noqa: E731
    else:
        fn = lambda s: 1.0  # noqa: E731
    return opt, torch.optim.lr_scheduler.LambdaLR(opt, fn)


def new_history(weights: Mapping[str, float]) -> dict[str, list]:
    """Empty loss history: one list per weighted term (of :data:`TERMS`, then any extra term of
    the loss, in ``weights``' order) plus ``"total"``."""
    extra = [k for k in weights if k not in TERMS]
    return {k: [] for k in (*TERMS, *extra, "total") if k == "total" or weights.get(k, 0.0) > 0}


def check_finite_terms(terms: Mapping[str, torch.Tensor], step: int) -> None:
    """Raise :class:`NonFiniteLossError` naming the first NaN/inf term of ``terms`` at ``step``."""
    for k, v in terms.items():
        if not bool(torch.isfinite(v).all()):
            raise NonFiniteLossError(
                f"loss term {k!r} is {float(v.detach())} at step {step}; stopping "
                f"(the last good checkpoint is kept)")


def optimize(model: torch.nn.Module, loss_fn: Callable, optimizer: torch.optim.Optimizer, scheduler,
             steps: int, *, start: int = 0, history: dict[str, list] | None = None,
             on_step: Callable[[int, dict], bool | None] | None = None) -> dict[str, list]:
    """Run optimizer steps ``start, ..., steps - 1`` of ``loss_fn(*model())["total"]``.

    Args:
        model: ``() -> (edge_rot, frames)``.
        loss_fn: ``(edge_rot, frames) -> dict`` of 0-dim tensors with a ``"total"`` entry.
        optimizer, scheduler: from :func:`make_optimizer` (L-BFGS gets a closure; the scheduler
            steps once per optimizer step).
        steps: the last step (the schedule's length); ``start``: the first (a resumed run).
        history: ``{term: [value per step]}`` to append to (default :func:`new_history` of the
            loss's ``weights``); a term not evaluated at a step records 0.
        on_step: called as ``on_step(step + 1, record)`` after each step with the unweighted
            terms of the step's first evaluation (checkpoints, progress bars); returning
            ``True`` stops the loop after that step.

    Returns:
        ``history``. Raises :class:`NonFiniteLossError` on a NaN/inf term (before the step).
    """
    if history is None:
        history = new_history(loss_fn.weights)
    lbfgs = isinstance(optimizer, torch.optim.LBFGS)
    for step in range(start, steps):
        record: dict[str, float] = {}

        def closure():
            optimizer.zero_grad(set_to_none=True)
            R, F = model()
            terms = loss_fn(R, F)
            check_finite_terms(terms, step)
            terms["total"].backward()
            if not record:
                record.update({k: float(v.detach()) for k, v in terms.items()})
            return terms["total"]

        if lbfgs:
            optimizer.step(closure)
        else:
            closure()
            optimizer.step()
        scheduler.step()
        for k in history:
            history[k].append(record.get(k, 0.0))
        if on_step is not None and on_step(step + 1, record) is True:
            break
    return history
